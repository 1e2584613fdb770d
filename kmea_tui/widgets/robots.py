"""Robots tab: pose, age of the last fix, relay destinations and messages sent per robot.

From a fusion node (``kmea fuse``) the state cell also names the cameras that saw the robot
(the body's ``source``, e.g. ``ok cam0+cam1``)."""

from __future__ import annotations

import math
from typing import Any

from rich.text import Text
from textual.app import ComposeResult
from textual.containers import Vertical
from textual.widgets import Static

from kmea_tui.widgets.live_table import DASH, LiveTable, fmt, show_line

COLUMNS = [
    ("name", "name"), ("markers", "markers"), ("x", "x m"), ("y", "y m"),
    ("theta", "θ°"), ("sigma", "σ mm"), ("age_s", "age s"), ("state", "state"),
    ("sent", "sent"), ("destinations", "UDP to"),
]


def robot_state(r: dict[str, Any], frozen: bool = False) -> str:
    """``frozen``: the daemon is stopped or silent, so nobody knows the robot's state."""
    if frozen:
        return "unknown"
    if r.get("stale"):
        return "STALE"
    return "ok" if r.get("valid") else "no fix"


def _sort_value(raw: dict[str, Any], col: str) -> Any:
    if col in ("name", "markers", "destinations"):
        v = raw.get(col)
        return ",".join(map(str, v)) if isinstance(v, list) else str(v or "")
    if col == "state":
        return robot_state(raw)
    v = raw.get(col)
    return v if isinstance(v, (int, float)) else None


def sent_cell(r: dict[str, Any]) -> str | Text:
    """Messages sent, with the failed sends (``send_errors``) when there are any."""
    sent, errors = r.get("sent", DASH), r.get("send_errors")
    if isinstance(errors, int) and errors > 0:
        return Text(f"{sent} ✗{errors}", style="bold yellow")
    return str(sent)


def robot_cells(r: dict[str, Any], frozen: bool = False) -> list[str | Text]:
    th = r.get("theta")
    markers = r.get("markers") or []
    dests = r.get("destinations") or []
    state = robot_state(r, frozen)
    cells: list[str | Text] = [
        str(r.get("name", "?")),
        "+".join(map(str, markers)) if isinstance(markers, list) else str(markers),
        fmt(r.get("x")), fmt(r.get("y")),
        fmt(math.degrees(th), ".0f") if isinstance(th, (int, float)) else DASH,
        fmt(r.get("sigma"), ".1f", 1000.0),
        fmt(r.get("age_s"), ".1f"),
        Text(state + (f" {src}" if (src := r.get("source")) and isinstance(src, str)
                       and not frozen else ""),
             style="bold red" if state == "STALE" else
             ("green" if state == "ok" else "bright_black" if frozen else "yellow")),
        sent_cell(r),
        # UDP is the only kind of destination: the prefix costs columns at 80x24.
        ", ".join(str(d).removeprefix("udp:") for d in dests)
        if isinstance(dests, list) else str(dests),
    ]
    return cells


class RobotsTable(LiveTable):
    def __init__(self, id: str | None = None) -> None:
        super().__init__(COLUMNS, sort_value=_sort_value, sort_column="name", id=id)


class RobotsPane(Vertical):
    frozen = False  # set by the app when the daemon is stopped or silent

    def compose(self) -> ComposeResult:
        yield Static("waiting for telemetry…", id="robots-summary", classes="summary")
        yield RobotsTable(id="robots-table")

    def update_robots(self, body: dict[str, Any]) -> None:
        robots = [r for r in body.get("robots", []) if isinstance(r, dict) and "name" in r]
        table = self.query_one(RobotsTable)
        table.sync({str(r["name"]): (r, robot_cells(r, self.frozen)) for r in robots})
        stale = sum(1 for r in robots if r.get("stale"))
        show_line(self.query_one("#robots-summary", Static), Text.assemble(
            ("NOT LIVE: last known " if self.frozen else "", "bold red"),
            (f"frame {body.get('frame', DASH)}", "bold"),
            f" · {len(robots)} robots · ",
            (f"{stale} stale", "bold red" if stale else ""),
            " · ", (table.sort_label() + " [s/S]", "italic")))
