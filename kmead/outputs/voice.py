"""One voice per robot, handed over make-before-break (docs/fusion.md, "One voice per robot").

Every speaker of a site that may speak to robot R (each camera's ``kmead`` with Zenoh on, the
active fusion node) listens on ``<site>/voice/R`` and says there what it does (JSON, at
most :data:`MAX_BYTES`):

- ``{"op": "say", "by", "kind", "seq", "q", "t"}``: a message it sent R (``seq`` the
  robot's sequence number; ``q`` how well it sees R: a camera's measurement sigma in m, 0
  for a node; ``t`` the pose's time);
- ``{"op": "claim", "by", "kind", "q"}``: it wants R's voice;
- ``{"op": "yield", "by", "kind", "seq", "to", "tk"}``: it stopped speaking to R and hands
  the voice to ``to`` (of kind ``tk``), or to anyone (``to`` null), after ``seq``.

The rules, the same in every speaker:

- **A holder keeps the voice until its successor is named.** A camera yields to a node's
  claim at once; to another camera only when that one sees R and it does not (a frame
  without R), or has seen R with less than half its sigma for :data:`BETTER_S`
  (hysteresis). A node yields to nobody while it is active (the election decides between
  nodes); a node that stops on purpose yields to the new active node's claim, else to the
  camera that measured R last.
- **A speaker starts only when named, or when nobody speaks**: the holder yielded to it,
  or the holder is known gone (a node's token went, a camera was dropped), or nobody ever
  spoke. A camera also starts when nothing was heard of the holder for :data:`QUIET_S`
  (a frozen node, before its lease runs out); a node never passes over a holder whose
  token is alive (a node: the election decides between nodes; a camera: it answers claims).
  After a silence, cameras that see R claim first and the best claim starts (lowest sigma,
  then id): no two cameras start together.
- **Two voices heard at once** (a race, two nodes cut off from each other): the one of
  lower rank stops when it hears the other (nodes before cameras, then the lower id).
- **One sequence per robot**: every speaker keeps the highest ``seq`` heard on R's key, and
  a speaker's next message is numbered above it; a yield names the seq of the message
  already on its way, if any (reserved when the relay was told to send); a robot taken
  from a holder gone without a yield (killed) skips :data:`TAKEOVER_SKIP` numbers, for the
  messages that may have reached the robot while their ``say`` was lost with the process.
  So ``seq`` never goes back or repeats across camera, node and camera handovers; it may
  skip.
- Tokens silence nobody: only a holder's traffic (``say``) keeps the others quiet, so a
  stranger's liveliness token changes nothing, and a node that is alive but not speaking
  for R leaves R to the cameras.

Everything heard is hostile: a message that does not parse, a name of no robot of ours, an
id or number out of bounds is counted in :attr:`Voice.bad` and ignored.

Threads: Zenoh's callback (:meth:`Voice._heard`) updates the table under :attr:`Voice.lock`
and may answer a node's claim at once (a ``yield`` put); :meth:`speak`, :meth:`said`,
:meth:`want`, :meth:`frame`, :meth:`release` are the owner's (its frame loop or the fusion
node's loop, under the owner's lock), so a message is never sent between a yield and the
seq it names.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from kmea.wire.jsonlimits import safe_loads

log = logging.getLogger("kmead.voice")

__all__ = ["CAMERA", "NODE", "QUIET_S", "Voice"]

NODE, CAMERA = "node", "camera"
# s: a holder heard nothing of for this long speaks no more, for the cameras (a frozen node:
# longer than a loaded node's pauses, shorter than the lease)
QUIET_S = 1.0
CLAIM_EVERY_S = 0.1  # s: a candidate repeats its claim at most this often
CLAIM_FRESH_S = 0.3  # s: a claim older than this is forgotten
HYSTERESIS = 0.5  # a camera takes a seen robot over only with less than half the sigma ...
BETTER_S = 1.0  # ... for this long (s)
MAX_BYTES = 512
MAX_CLAIMS = 64  # claimants remembered per robot
TAKEOVER_SKIP = 4  # seq numbers skipped when a robot is taken from a holder gone silent
MAX_SEQ = 2**32 - 1  # the binary pose's seq is a uint32
_ID_RE = re.compile(r"^[A-Za-z0-9_-]{1,40}$")


def _rank(kind: str, speaker: str) -> tuple[int, str]:
    """Who stays when two speak at once: nodes before cameras, then the lower id."""
    return (0 if kind == NODE else 1, speaker)


@dataclass
class _Robot:
    speaking: bool = False
    holder: str | None = None  # the other speaker heard last (None: nobody, or it yielded)
    holder_kind: str = ""
    heard: float = -math.inf  # monotonic time the holder was last heard (say) or named
    seq: int = 0  # the highest seq heard on the key or sent
    t: float = -math.inf  # the newest pose time heard said (a new speaker starts after it)
    granted: str | None = None  # the speaker that yielded to this one
    claims: dict[str, tuple[str, float, float]] = field(default_factory=dict)  # by -> kind, q, t
    claimed: float = -math.inf  # this speaker's last claim
    claiming_since: float = math.inf  # start of this speaker's current run of claims
    q: float = math.inf  # this speaker's view of R (its last measurement's sigma)
    seen: float = -math.inf  # monotonic time of this speaker's last fix of R
    prev_seen: float = -math.inf  # the fix before
    lost: bool = False  # the voice went since the owner last looked (undeclare outputs)
    better: tuple[str, float] | None = None  # a camera seeing it much better, since when


class Voice:
    """This speaker's side of the rules (module docstring) on an open Zenoh session.

    ``known(name)``: a robot of ours; ``alive(speaker, kind)``: False when that speaker is
    known to be gone (its token went), else True; ``successor(name)``: who takes R when
    this speaker stops on purpose, ``(id, kind)`` or None (default: the best fresh claim);
    ``on_quiet(name)``: this speaker no longer speaks for R (undeclare its outputs);
    ``listen_s``: how long to listen before speaking to a robot nobody was heard on."""

    def __init__(self, session: Any, site: str, me: str, kind: str,
                 known: Callable[[str], bool],
                 alive: Callable[[str, str], bool] | None = None,
                 successor: Callable[[str], tuple[str, str] | None] | None = None,
                 on_quiet: Callable[[str], None] | None = None,
                 listen_s: float = QUIET_S) -> None:
        self.session = session
        self.site = site
        self.me = me
        self.kind = kind
        self.known = known
        self.alive = alive
        self.successor = successor
        self.on_quiet = on_quiet
        self.listen_until = time.monotonic() + listen_s
        self.stopping = False  # a node stopping on purpose: it yields to a node's claim
        self.lock = threading.Lock()
        self.robots: dict[str, _Robot] = {}
        self.bad = 0
        self.nodes_said: dict[str, float] = {}  # node id -> monotonic time of its last say
        self.handovers = 0  # yields made
        self.sub = session.declare_subscriber(f"{site}/voice/*", self._heard)

    # ------------------------------------------------------------------ Zenoh's thread
    def _heard(self, sample: Any) -> None:
        key = str(sample.key_expr)
        try:
            name = key.rsplit("/", 1)[-1]
            body = safe_loads(sample.payload.to_bytes(), MAX_BYTES, 1)
            op, by, kind, seq, q, to, tk, t = _check(body)
        except (ValueError, TypeError):
            self.bad += 1
            return
        if by == self.me or not self.known(name):
            return
        now = time.monotonic()
        answer: dict | None = None
        with self.lock:
            r = self._robot(name)
            if seq is not None:
                r.seq = max(r.seq, seq)
            if op == "say":
                if kind == NODE:
                    if len(self.nodes_said) >= MAX_CLAIMS and by not in self.nodes_said:
                        self.nodes_said.pop(min(self.nodes_said, key=lambda k: self.nodes_said[k]))
                    self.nodes_said[by] = now
                if t is not None:
                    r.t = max(r.t, t)
                if r.speaking and _rank(kind, by) < _rank(self.kind, self.me):
                    r.speaking, r.lost = False, True  # two voices: the better one stays
                if not r.speaking:
                    r.holder, r.holder_kind, r.heard = by, kind, now
                    if r.granted is not None and r.granted != by:
                        r.granted = None  # someone else speaks now
            elif op == "claim":
                if len(r.claims) >= MAX_CLAIMS:  # bounded (hostile ids): the stale go
                    r.claims = {b: c for b, c in r.claims.items()
                                if now - c[2] < CLAIM_FRESH_S}
                if len(r.claims) < MAX_CLAIMS:
                    r.claims[by] = (kind, q if q is not None else math.inf, now)
                if r.speaking and kind == NODE and (self.kind == CAMERA or self.stopping):
                    answer = self._yield(r, by, kind)
            elif op == "yield":
                if to == self.me:
                    r.granted = by
                if r.holder == by or r.holder is None:
                    r.holder, r.holder_kind = to, tk or ""
                    r.heard = now if to is not None else -math.inf
        if answer is not None:
            self._put(name, answer)

    def nodes_speaking(self, within_s: float) -> set[str]:
        """The nodes heard saying they spoke to a robot in the last ``within_s`` s."""
        now = time.monotonic()
        with self.lock:
            return {by for by, at in self.nodes_said.items() if now - at < within_s}

    # ------------------------------------------------------------------ the owner's
    def want(self, name: str, q: float | None) -> None:
        """A camera's fix of ``name`` with sigma ``q`` (m) this frame."""
        with self.lock:
            r = self._robot(name)
            r.q = q if q is not None and math.isfinite(q) and q >= 0 else 1.0
            r.prev_seen, r.seen = r.seen, time.monotonic()

    def speak(self, tr: Any, valid: bool, t: float | None = None) -> bool:
        """May this speaker send robot ``tr``'s next message, a pose at time ``t`` (``tr.seq``
        is then raised above every seq heard)? Claims the voice when it wants it and may not
        have it; a speaker given the voice starts with a pose newer than its predecessor's
        last (a node that lags behind the cameras does not send the robot back in time)."""
        now = time.monotonic()
        out: dict | None = None
        with self.lock:
            r = self._robot(tr.name)
            quiet = r.lost
            r.lost = False
            if not r.speaking and not self.stopping:
                start, out = self._may_start(r, now, valid)
                if start and t is not None and t < r.t:
                    start = False
                if start:
                    if r.granted is None and r.holder is not None:
                        # Taken without a hand-over (the holder was killed or frozen): its
                        # last messages may have reached the robot while their say did not.
                        r.seq += TAKEOVER_SKIP
                    r.speaking, r.granted = True, None
                    r.claims.clear()
                    r.claiming_since = math.inf
            if r.speaking:
                tr.seq = max(tr.seq, r.seq)
                r.seq = tr.seq + 1  # the message about to go: a yield names it
                speaking = True
            else:
                speaking = False
        if quiet and not speaking and self.on_quiet is not None:
            self.on_quiet(tr.name)
        if out is not None:
            self._put(tr.name, out)
        return speaking

    def _may_start(self, r: _Robot, now: float, valid: bool) -> tuple[bool, dict | None]:
        """Under the lock: (start speaking now, a claim to send)."""
        if self.kind == CAMERA and (not valid or now - r.seen > QUIET_S):
            return False, None  # a camera takes a robot only with a fix of it
        if r.granted is not None:
            return True, None
        known_gone = r.holder is None or (self.alive is not None
                                          and not self.alive(r.holder, r.holder_kind))
        if self.kind == NODE:
            if known_gone:
                return now >= self.listen_until, None
            # A node holder alive (its token) keeps its robots: the election decides
            # between nodes. A camera holder answers a claim at once (a frozen one is
            # dropped by the node after the lease: known gone then); silence proves
            # nothing, a camera that does not see the robot says nothing.
            return False, self._claim(r, now)
        if not known_gone and now - r.heard < QUIET_S:
            if r.holder_kind == NODE:
                return False, None  # a node speaks: the cameras listen
            return False, self._claim(r, now)
        if now < self.listen_until:
            return False, None  # a voice already there may not have been heard yet
        # Cameras after a silence: the best fresh claim starts, once it has claimed for a
        # claim period (the others' claims have had time to arrive).
        claim = self._claim(r, now)
        mine = (r.q, self.me)
        for by, (kind, q, t) in r.claims.items():
            if now - t < CLAIM_FRESH_S and (kind == NODE or (q, by) < mine):
                return False, claim
        return now - r.claiming_since >= CLAIM_EVERY_S, claim

    def _claim(self, r: _Robot, now: float) -> dict | None:
        if now - r.claimed < CLAIM_EVERY_S:
            return None
        # A camera claims at most once a frame: when its last claim came at its previous fix
        # of R, a long gap is a slow frame rate (a Pi in a full detection, an emulated or
        # loaded machine), not a break in the run; else a camera below 2 frames/s would
        # begin a new run at every frame and never speak.
        continued = (self.kind == CAMERA and math.isfinite(r.claimed)
                     and r.claimed >= r.prev_seen)
        if now - r.claimed > 2 * CLAIM_EVERY_S + CLAIM_FRESH_S and not continued:
            r.claiming_since = now  # a new run of claims
        r.claimed = now
        return {"op": "claim", "by": self.me, "kind": self.kind,
                "q": r.q if math.isfinite(r.q) else None}

    def said(self, tr: Any, valid: bool, t: float | None = None) -> None:
        """Robot ``tr``'s message (``tr.seq``, its pose at ``t``) went out: say so."""
        with self.lock:
            r = self._robot(tr.name)
            r.seq = max(r.seq, tr.seq)
            if t is not None and math.isfinite(t):
                r.t = max(r.t, t)
            q = r.q if self.kind == CAMERA and math.isfinite(r.q) else 0.0
        body: dict[str, Any] = {"op": "say", "by": self.me, "kind": self.kind,
                                "seq": tr.seq, "q": q, "valid": bool(valid)}
        if t is not None and math.isfinite(t):
            body["t"] = t
        self._put(tr.name, body)

    def frame(self, seen: set[str]) -> None:
        """A camera's frame with fixes of ``seen``: hand a robot it speaks for to another
        camera that claims it while this one lost it, or sees it much better."""
        now = time.monotonic()
        outs: list[tuple[str, dict]] = []
        quiet: list[str] = []
        with self.lock:
            for name, r in self.robots.items():
                if not r.speaking:
                    continue
                best: tuple[float, str] | None = None
                for by, (kind, q, t) in r.claims.items():
                    if kind == CAMERA and now - t < CLAIM_FRESH_S and (best is None
                                                                      or (q, by) < best):
                        best = (q, by)
                if best is None:
                    r.better = None
                    continue
                # Much better (under HYSTERESIS of this one's sigma) for BETTER_S on end:
                # a camera's sigma is noisy from frame to frame, a hand-over is not.
                if best[0] < HYSTERESIS * r.q:
                    if r.better is None or r.better[0] != best[1]:
                        r.better = (best[1], now)
                else:
                    r.better = None
                if name not in seen or (r.better is not None and now - r.better[1] >= BETTER_S):
                    r.better = None
                    outs.append((name, self._yield(r, best[1], CAMERA)))
                    quiet.append(name)
                    r.lost = False
        for name, msg in outs:
            self._put(name, msg)
        for name in quiet:
            if self.on_quiet is not None:
                self.on_quiet(name)

    def release(self) -> None:
        """This speaker stops on purpose: each robot it speaks for goes to its successor
        (``successor``, else the best fresh claim); a robot with none stays (its valid=0
        follows)."""
        now = time.monotonic()
        outs: list[tuple[str, dict]] = []
        with self.lock:
            for name, r in self.robots.items():
                if not r.speaking:
                    continue
                to = self.successor(name) if self.successor is not None else None
                if to is None:
                    fresh = [(_rank(k, by), by, k) for by, (k, _q, t) in r.claims.items()
                             if now - t < CLAIM_FRESH_S]
                    to = (min(fresh)[1], min(fresh)[2]) if fresh else None
                if to is not None:  # else it stays: the robot gets this one's valid=0
                    outs.append((name, self._yield(r, *to)))
        for name, msg in outs:
            self._put(name, msg)

    def speaking(self) -> set[str]:
        with self.lock:
            return {n for n, r in self.robots.items() if r.speaking}

    def close(self) -> None:
        with contextlib.suppress(Exception):  # a session already closed
            self.sub.undeclare()

    # ------------------------------------------------------------------ pieces
    def _robot(self, name: str) -> _Robot:
        r = self.robots.get(name)
        if r is None:
            r = self.robots[name] = _Robot()
        return r

    def _yield(self, r: _Robot, to: str | None, kind: str | None) -> dict:
        """Under the lock: stop speaking for ``r``, naming ``to``."""
        r.speaking, r.lost = False, True
        r.holder, r.holder_kind = to, kind or ""
        r.heard = time.monotonic() if to is not None else -math.inf
        self.handovers += 1
        return {"op": "yield", "by": self.me, "kind": self.kind, "seq": r.seq, "to": to,
                "tk": kind}

    def _put(self, name: str, body: dict) -> None:
        try:
            self.session.put(f"{self.site}/voice/{name}", json.dumps(body).encode())
        except Exception as e:  # a session closing
            log.debug("voice: put failed: %s", e)


def _check(body: Any) -> tuple[str, str, str, int | None, float | None, str | None,
                               str | None, float | None]:
    """A voice message's fields, checked (ValueError for anything else)."""
    if not isinstance(body, dict):
        raise ValueError("expected a JSON object")
    op, by, kind = body.get("op"), body.get("by"), body.get("kind")
    if op not in ("say", "claim", "yield") or kind not in (NODE, CAMERA) \
            or not isinstance(by, str) or not _ID_RE.match(by):
        raise ValueError("op, by or kind")
    seq = body.get("seq")
    if op != "claim" and (isinstance(seq, bool) or not isinstance(seq, int)
                          or not 0 <= seq <= MAX_SEQ):
        raise ValueError("seq")
    q = body.get("q")
    if q is not None and (isinstance(q, bool) or not isinstance(q, (int, float))
                          or not math.isfinite(q) or q < 0):
        raise ValueError("q")
    to, tk = body.get("to"), body.get("tk")
    if op == "yield" and to is not None and (not isinstance(to, str) or not _ID_RE.match(to)
                                             or tk not in (NODE, CAMERA)):
        raise ValueError("to")
    t = body.get("t")
    if t is not None and (isinstance(t, bool) or not isinstance(t, (int, float))
                          or not math.isfinite(t)):
        raise ValueError("t")
    return (op, by, kind, seq if op != "claim" else None,
            float(q) if q is not None else None, to if op == "yield" else None,
            tk if op == "yield" else None, float(t) if t is not None else None)
