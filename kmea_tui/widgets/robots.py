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

from kmea.wire.destinations import THIS_MACHINE_ONLY, this_machine_only
from kmea_tui.widgets.live_table import DASH, LiveTable, fmt, show_line
from kmea_tui.widgets.status_bar import CLOCK_ALERT_S, clock_text

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


def refused_now(r: dict[str, Any]) -> list[str]:
    """The robot's destinations that refuse its datagrams now (the daemon's ``refused``)."""
    dests, refused = r.get("destinations"), r.get("refused")
    if not isinstance(dests, list) or not isinstance(refused, list):
        return []
    return [d for d in dests if d in refused]


def sent_cell(r: dict[str, Any]) -> str | Text:
    """Messages sent, with the failed sends (``send_errors``) when there are any.

    A destination nobody listens on (the default ones on a first start) refuses every
    datagram: the count would say "sent" although nothing arrives, and ✗N would look like a
    fault of kmead. The cell says "no listener" instead (with several destinations, how
    many of them: "no listener 1/2"; the destinations column shows which, in yellow).
    Refusals (``send_refused``) are not counted as ✗ errors."""
    sent, errors = r.get("sent", DASH), r.get("send_errors")
    refused = r.get("send_refused")
    if isinstance(errors, int) and isinstance(refused, int):
        errors -= refused
    if isinstance(errors, int) and errors > 0:
        return Text(f"{sent} ✗{errors}", style="bold yellow")
    if nobody := refused_now(r):
        n = len(r.get("destinations") or [])
        return Text(NO_LISTENER + (f" {len(nobody)}/{n}" if len(nobody) < n else ""),
                    style="yellow")
    return str(sent)


LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "[::1]")
NO_LISTENER = "no listener"


def destination_text(dest: str) -> str:
    """``udp:127.0.0.1:9001`` as ``:9001``: on this machine only the port tells them apart,
    and the full address does not fit at 80x24; other hosts keep ``host:port``."""
    d = str(dest).removeprefix("udp:")  # UDP is the only kind of destination
    host, sep, port = d.rpartition(":")
    if sep and (host in LOOPBACK_HOSTS or host.startswith("127.")):
        return f":{port}"
    return d


def destinations_cell(r: dict[str, Any]) -> str | Text:
    """The destinations; those nobody listens on in yellow (see :func:`sent_cell`)."""
    dests = r.get("destinations") or []
    if not isinstance(dests, list):
        return str(dests)
    nobody = refused_now(r)
    if not nobody:
        return ", ".join(destination_text(d) for d in dests)
    text = Text()
    for i, d in enumerate(dests):
        if i:
            text.append(", ")
        text.append(destination_text(d), style="yellow" if d in nobody else "")
    return text


def robot_cells(r: dict[str, Any], frozen: bool = False,
                since: float = 0.0) -> list[str | Text]:
    """One robot's row. ``since``: seconds since the body arrived, added to the age of a
    robot's last fix while the data is not live (a frozen 0.0 would say "just seen")."""
    th = r.get("theta")
    markers = r.get("markers") or []
    state = robot_state(r, frozen)
    age = r.get("age_s")
    if frozen and isinstance(age, (int, float)):
        age += since
    cells: list[str | Text] = [
        str(r.get("name", "?")),
        "+".join(map(str, markers)) if isinstance(markers, list) else str(markers),
        fmt(r.get("x")), fmt(r.get("y")),
        fmt(math.degrees(th), ".0f") if isinstance(th, (int, float)) else DASH,
        fmt(r.get("sigma"), ".1f", 1000.0),
        fmt(age, ".0f" if isinstance(age, (int, float)) and age >= 100 else ".1f"),
        Text(state + (f" {src}" if (src := r.get("source")) and isinstance(src, str)
                       and not frozen else ""),
             style="bold red" if state == "STALE" else
             ("green" if state == "ok" else "bright_black" if frozen else "yellow")),
        sent_cell(r),
        destinations_cell(r),
    ]
    return cells


class RobotsTable(LiveTable):
    def __init__(self, id: str | None = None) -> None:
        super().__init__(COLUMNS, sort_value=_sort_value, sort_column="name", id=id)


class RobotsPane(Vertical):
    frozen = False  # set by the app when the daemon is stopped or silent
    inputs: list = []  # a fusion node's cameras (its status), never mutated: replaced

    def compose(self) -> ComposeResult:
        yield Static("waiting for telemetry…", id="robots-summary", classes="summary")
        yield RobotsTable(id="robots-table")

    def update_robots(self, body: dict[str, Any], since: float = 0.0) -> None:
        """Show one ``robots`` body; ``since``: seconds since it arrived (see robot_cells)."""
        robots = [r for r in body.get("robots", []) if isinstance(r, dict) and "name" in r]
        table = self.query_one(RobotsTable)
        table.sync({str(r["name"]): (r, robot_cells(r, self.frozen, since)) for r in robots})
        stale = sum(1 for r in robots if r.get("stale"))
        show_line(self.query_one("#robots-summary", Static), Text.assemble(
            # Not live: the status line says the last frame (one number on the screen).
            ("NOT LIVE: last known poses", "bold red") if self.frozen
            else (f"frame {body.get('frame', DASH)}", "bold"),
            f" · {len(robots)} robots · ",
            (f"{stale} stale", "bold red" if stale else ""),
            (f" · {THIS_MACHINE_ONLY}" if this_machine_only(robots) else "", "yellow"),
            " · ", (table.sort_label() + " [s/S]", "italic"), cameras_text(self.inputs)))


def cameras_text(inputs: list) -> Text:
    """A fusion node's cameras with their state and clock offset (``cam0 used +2 ms``);
    an offset beyond CLOCK_ALERT_S in red."""
    t = Text()
    for cam in inputs:
        if not isinstance(cam, dict):
            continue
        off = cam.get("clock_offset_s")
        far = isinstance(off, (int, float)) and abs(off) > CLOCK_ALERT_S
        t.append(f" · {cam.get('label', '?')} {cam.get('state', '?')} ")
        t.append(f"clock {clock_text(off)}", "bold red" if far else "")
    return t
