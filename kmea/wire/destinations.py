"""Where the robots' datagrams go, as a technician needs to know it (stdlib: the UI uses it).

A configuration whose every robot destination is this machine (``udp:127.0.0.1:9001``, the
built-in default) reaches no robot: the daemon's start-up log, ``kmea doctor`` and the UI's
Robots tab say so in the same words (:data:`THIS_MACHINE_ONLY`).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

__all__ = ["THIS_MACHINE_ONLY", "is_loopback", "this_machine_only"]

THIS_MACHINE_ONLY = "robots' UDP poses go to this machine only"
_LOOPBACK = ("localhost", "[::1]", "::1")


def is_loopback(destination: str) -> bool:
    """``udp:HOST:PORT`` (or ``HOST:PORT``) with a loopback host."""
    host = str(destination).removeprefix("udp:").rpartition(":")[0]
    return host in _LOOPBACK or host.startswith("127.")


def this_machine_only(robots: Iterable[Mapping[str, Any]]) -> bool:
    """True when there are robots and every destination of every robot is loopback (a
    robot with none sends nowhere, which says nothing either way)."""
    dests = [d for r in robots for d in (r.get("destinations") or [])]
    return bool(dests) and all(is_loopback(d) for d in dests)
