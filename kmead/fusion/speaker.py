"""The fusion node's voice: its role in the election and its token, its robot outputs while
active, its turn per robot (:mod:`kmead.outputs.voice`) and the hand-over when it stops on
purpose (docs/fusion.md, "Two nodes" and "One voice per robot").

- While the node is ``active`` its relay speaks, robot by robot, once the voice gives it
  the robot: a camera still speaking is asked (a claim) and hands over before the node's
  first message; a robot nobody speaks to (the active node before it was killed) is taken
  at once.
- Stopped on purpose (SIGINT, SIGTERM, ``--frames``, systemd's stop): the node's token
  becomes ``<site>/fusion/<id>/stopping``, so a standby claims the voice by the election's
  rule, and this node goes on fusing and speaking until each robot it speaks for is
  claimed (at most :data:`HANDOVER_S`, only while a standby is there); then the robots
  left go back to the camera that measured each last (``release``). A robot nobody takes
  gets its ``valid=0`` at the close, as before.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable
from typing import Any

from kmead.fusion.election import Election
from kmead.outputs.voice import CAMERA, NODE, Voice

__all__ = ["HANDOVER_S", "Speaker"]

HANDOVER_S = 1.0  # s: the longest an orderly stop waits for the new active node's claims
POLL_S = 0.001


class Speaker:
    """The node's side of who speaks (module docstring); ``node`` is its
    :class:`kmead.fusion.node.FusionNode` (session, relay, cameras, fusion, event)."""

    def __init__(self, node: Any) -> None:
        self.node = node
        self.election = Election(node.node_id, 2 * node.lease_s, time.monotonic())
        self.role_changes: list[tuple[float, str]] = []  # (time.time(), role)
        self._token: Any = None
        self.voice = Voice(node.session, node.site, node.node_id, NODE,
                           known=lambda name: name in node.names, alive=self._alive,
                           successor=self._successor, on_quiet=self._quiet, listen_s=0.0)
        node.relay.voice = self.voice
        self._declare_role()

    # ------------------------------------------------------------------ the voice's questions
    def _alive(self, speaker: str, kind: str) -> bool:
        """False when ``speaker`` is known gone: a node without a token, a camera dropped."""
        if kind == NODE:
            return speaker in self.election.others
        cam = self.node.cameras.get(speaker)
        return cam is None or cam.state not in ("gone", "silent")

    def _successor(self, name: str) -> tuple[str, str] | None:
        """The camera that measured robot ``name`` last (still used), for a hand-back."""
        seen = self.node.fusion.seen.get(name)
        if seen is None:
            return None
        used = [(t, cam) for cam, t in seen.last.items()
                if (c := self.node.cameras.get(cam)) is not None and c.state == "used"]
        return (max(used)[1], CAMERA) if used else None

    def _quiet(self, name: str) -> None:
        if self.node.zenoh_out is not None:
            self.node.zenoh_out.quiet(name)

    # ------------------------------------------------------------------ the election
    def _declare_role(self) -> None:
        """The token of this node's role: the new one first, then the old one goes."""
        old = self._token
        self._token = self.node.session.liveliness().declare_token(
            f"{self.node.site}/fusion/{self.node.node_id}/{self.election.role}")
        if old is not None:
            old.undeclare()

    def elect(self, now: float, stalled: bool = False) -> None:
        """The election's rule (in the loop, under the node's lock)."""
        speaking = self.voice.nodes_speaking(self.node.lease_s)
        role = self.election.decide(now, stalled, speaking)
        while role is not None:
            self._set_role(role)
            role = self.election.decide(now, speaking=speaking)

    def _set_role(self, role: str) -> None:
        node = self.node
        relay = node.relay
        self.role_changes.append((time.time(), role))
        if role == "active":
            from kmead.outputs.zenoh import FUSION_NODE_NAME, ZenohOutput

            node.zenoh_out = ZenohOutput.open(node.z, node.session, FUSION_NODE_NAME)
            relay.sink = node.zenoh_out.send
            relay.muted = False
        elif node.zenoh_out is not None:
            relay.muted = True
            relay.sink = None
            node.zenoh_out.close()
            node.zenoh_out = None
        self._declare_role()
        text = {"active": "active: this node speaks to the robots (each once the camera "
                          "speaking to it has handed over)",
                "standby": "standby: another node speaks to the robots, or this one will "
                           "when none does",
                "starting": "stepped down (it did not run for longer than the lease); "
                            "watching the site again"}[role]
        node.event("warning" if role == "starting" else "info",
                   f"fusion node {node.node_id[:8]}: {text}")

    # ------------------------------------------------------------------ an orderly stop
    def hand_over(self, pump: Callable[[], int]) -> None:
        """The node was stopped on purpose (its loop, after the stop): make before break.
        Its token says ``stopping``; while a standby is there, this node keeps fusing and
        speaking (``pump`` handles what arrived) until the new active node has claimed
        every robot this one speaks for and that is not stale, at most :data:`HANDOVER_S`.
        The rest go back to the camera that measured each last, at once."""
        node = self.node
        if self.election.role != "active":
            return
        self.election.stop()
        self.voice.stopping = True
        with node.lock:
            self._declare_role()
        standby = any("standby" in roles for roles in self.election.others.values())
        end = time.monotonic() + (HANDOVER_S if standby else 0.0)
        while time.monotonic() < end:
            with node.lock:
                relay = node.relay
                if relay is None:
                    return
                fresh = {n for n, tr in relay.channels.items() if not tr.stale}
                if not self.voice.speaking() & fresh:
                    break
                n = pump()
            if not n:
                time.sleep(POLL_S)
        with node.lock:  # the rest to the cameras now, not after the node's close
            self.voice.release()
        node.event("info", f"fusion node {node.node_id[:8]}: stopping; the robots go to "
                           f"{'the new active node' if standby else 'the cameras'}")

    def close(self) -> None:
        self.voice.close()
        if self._token is not None:
            with contextlib.suppress(Exception):  # a session already closed
                self._token.undeclare()
            self._token = None
