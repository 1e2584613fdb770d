"""Which of a site's fusion nodes speaks to the robots (docs/fusion.md, "Two nodes")."""

from __future__ import annotations

from collections.abc import Set as AbstractSet

__all__ = ["Election"]


class Election:
    """Which of the site's fusion nodes speaks to the robots; the node's loop calls it.

    Each node holds one liveliness token ``<site>/fusion/<id>/<role>``: ``id`` its Zenoh
    session id, ``role`` one of ``starting`` (the first ``grace_s`` after its start, two
    leases: it watches the site for the tokens of nodes already there; the peers retry a
    lost connection every half lease, kmead.outputs.zenoh_session), ``standby`` or
    ``active``. The rule, the same in every node, so that nodes that see the same tokens agree:

    - a standby claims the voice when no active token is alive and it has the lowest id of
      the standbys: a node that starts never takes the voice from a running active one,
      whatever its id, and never claims before it has watched the site for ``grace_s``;
    - an active node that hears another active one with a lower id speak to a robot steps
      down to standby (two nodes cut off from each other both claim; when they meet again
      one voice is left). Its token alone is not enough: a token is no voice, and a peer
      that holds one without speaking (a stranger) must not silence the node;
    - an active node that finds it has not run for longer than the lease (the machine or
      the process was frozen; a standby has taken over meanwhile) steps down before it
      sends anything, and starts over (``grace_s`` of watching).
    """

    def __init__(self, node_id: str, grace_s: float, now: float) -> None:
        self.id = node_id
        self.grace_s = grace_s
        self.role = "starting"
        self.since = now  # start of "starting"
        self.others: dict[str, set[str]] = {}  # node id -> its roles' tokens alive

    def token(self, node_id: str, role: str, alive: bool) -> None:
        if node_id == self.id:
            return
        roles = self.others.setdefault(node_id, set())
        (roles.add if alive else roles.discard)(role)
        if not roles:
            del self.others[node_id]

    def stop(self) -> None:
        """Stopped on purpose: ``stopping`` until the end (a standby claims meanwhile)."""
        self.role = "stopping"

    def decide(self, now: float, stalled: bool = False,
               speaking: AbstractSet[str] = frozenset()) -> str | None:
        """The new role when it changes, else None. ``speaking``: the ids of the nodes heard
        speaking to a robot lately (:meth:`kmead.outputs.voice.Voice.nodes_speaking`)."""
        if self.role == "stopping":
            return None
        actives = {n for n, roles in self.others.items() if "active" in roles}
        if self.role == "active":
            if stalled:
                self.role, self.since = "starting", now
            elif any(n < self.id for n in actives & speaking):
                self.role = "standby"
            else:
                return None
            return self.role
        if self.role == "starting":
            if now - self.since < self.grace_s:
                return None
            self.role = "standby"
            return self.role
        standbys = {n for n, roles in self.others.items() if "standby" in roles}
        if actives or min([self.id, *standbys]) != self.id:
            return None
        self.role = "active"
        return self.role
