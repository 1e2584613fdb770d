"""Textual messages posted by the app's background workers to the UI."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from textual.message import Message


@dataclass
class TelemetryBatch(Message):
    """What arrived since the previous batch, coalesced.

    Attributes:
        latest: the newest body per topic (older ones of the same topic were dropped).
        events: every ``event`` and ``log`` message, oldest first, as (topic, body)
            (these are a history, so they are never coalesced; at most ``EVENT_BACKLOG``).
        received: messages received so far in total.
        coalesced: messages dropped so far because a newer one of the same topic came.
        ended: the source has no more data (a finished recording).
        raw: the newest message per topic not decoded yet, as received (``[topic, body]``
            frames), for the topics the app decodes only when a pane shows them.
    """

    latest: dict[str, dict[str, Any]]
    events: list[tuple[str, dict[str, Any]]] = field(default_factory=list)
    received: int = 0
    coalesced: int = 0
    ended: bool = False
    raw: dict[str, list[bytes]] = field(default_factory=dict)


@dataclass
class ConnectionChanged(Message):
    """The control ping result changed: ``ok`` is False when the daemon does not answer;
    ``role``: what the daemon says this client's key is ("operator", "viewer"; None
    without keys)."""

    ok: bool
    detail: str = ""
    role: str | None = None


@dataclass
class ControlReply(Message):
    """The reply to a control request the UI made (``reply["ok"]`` says if it worked)."""

    cmd: str
    args: dict[str, Any]
    reply: dict[str, Any]


@dataclass
class ControlRequest(Message):
    """A widget asks the app to send a control command to the daemon."""

    cmd: str
    args: dict[str, Any] = field(default_factory=dict)
