"""Markers tab: every marker the daemon reports, with its leave-one-out error.

Whether a marker has moved is the daemon's decision (``markers[].moved``, with its evidence
``moved_offset``/``moved_threshold``/``moved_frames``; see ``kmea/stats/moved.py``): this tab only
shows it.
"""

from __future__ import annotations

import math
import statistics
from typing import Any

from rich.text import Text
from textual.app import ComposeResult
from textual.containers import Vertical
from textual.widgets import Static

from kmea_tui.widgets.live_table import DASH, LiveTable, fmt, show_line

COLUMNS = [
    ("id", "id"), ("map", "map"), ("det", "det"), ("x", "x m"), ("y", "y m"),
    ("yaw", "yaw°"), ("map_x", "map x"), ("map_y", "map y"), ("error", "LOO mm"),
    ("flags", "flags"), ("plane", "plane"),
]


def moved_ids(markers: list[dict[str, Any]]) -> set[int]:
    """Ids the daemon reports as moved."""
    return {int(m["id"]) for m in markers if m.get("moved")}


def moved_note(m: dict[str, Any]) -> str:
    """The daemon's evidence for one moved marker: ``7 21>10 mm`` (median offset over its
    threshold)."""
    off, thr = m.get("moved_offset"), m.get("moved_threshold")
    if isinstance(off, (int, float)) and isinstance(thr, (int, float)):
        return f"{m['id']} {off * 1e3:.0f}>{thr * 1e3:.0f} mm"
    return str(m["id"])


FLAGS_HELP = (("!", "moved: the daemon's decision (median offset over its last frames "
                    "above the marker's threshold)"),
              ("A", "ambiguous pose"), ("F", "pose flipped"),
              ("S", "suspect: corners hidden or at the image border, not a reference"),
              ("R", "rejected by a robust estimator"))


def flags_of(m: dict[str, Any]) -> str:
    """``!`` moved (the daemon's decision), ``A`` ambiguous pose, ``F`` pose flipped, ``S``
    suspect (detected corners not trustworthy this frame: estimated, not a reference),
    ``R`` rejected by a robust estimator this frame."""
    return "".join(ch for ch, on in (("!", m.get("moved")), ("A", m.get("ambiguous")),
                                     ("F", m.get("flipped")), ("S", m.get("suspect")),
                                     ("R", m.get("rejected")))
                   if on)


def plane_of(m: dict[str, Any]) -> str:
    """Where the estimator put a marker of unknown plane (not in the map, not on a configured
    robot): the daemon's ``plane`` ("floor", "plane N" or "free"), a dash for the others."""
    p = m.get("plane")
    return p if isinstance(p, str) and p else DASH


def _sort_value(raw: dict[str, Any], col: str) -> Any:
    if col == "id":
        return int(raw.get("id", 0))
    if col == "plane":
        return raw.get("plane") or None
    if col in ("map", "det"):
        return bool(raw.get("in_map" if col == "map" else "detected"))
    if col == "flags":
        return raw.get("_flags", "") or None
    v = raw.get(col)
    return v if isinstance(v, (int, float)) else None


class MarkersTable(LiveTable):
    # Shown by Textual's help panel (``?`` or Ctrl+P "Keys") while the table has focus.
    # Compact: it must fit the help panel at 80x24.
    HELP = "\n".join([
        "**Markers**: map markers and detected others. *LOO mm*: leave-one-out error.",
        "",
        *(f"`{ch}` {text.split(':')[0]}  " for ch, text in FLAGS_HELP),
        "",
        "Rows: **red** moved, dim unseen, yellow suspect, cyan not in the map.",
        "*plane*: where a marker of unknown plane was put (floor, plane N, free).",
        "`s`/`S` sort.",
    ])

    def __init__(self, id: str | None = None) -> None:
        super().__init__(COLUMNS, sort_value=_sort_value, sort_column="id", id=id)


def marker_cells(m: dict[str, Any]) -> list[str | Text]:
    yaw = m.get("yaw")
    cells: list[str | Text] = [
        str(m.get("id")),
        "yes" if m.get("in_map") else "no",
        "yes" if m.get("detected") else "no",
        fmt(m.get("x")), fmt(m.get("y")),
        fmt(math.degrees(yaw), ".0f") if isinstance(yaw, (int, float)) else DASH,
        fmt(m.get("map_x")), fmt(m.get("map_y")),
        fmt(m.get("error"), ".1f", 1000.0),
        flags_of(m),
        plane_of(m),
    ]
    if m.get("moved"):
        return [Text(c, style="bold red") if isinstance(c, str) else c for c in cells]
    if not m.get("detected"):
        return [Text(c, style="bright_black") if isinstance(c, str) else c for c in cells]
    if m.get("suspect"):
        return [Text(c, style="yellow") if isinstance(c, str) else c for c in cells]
    if not m.get("in_map"):
        return [Text(c, style="cyan") if isinstance(c, str) else c for c in cells]
    return cells


class MarkersPane(Vertical):
    """Summary line and the live markers table."""

    def compose(self) -> ComposeResult:
        yield Static("waiting for telemetry…", id="markers-summary", classes="summary")
        yield MarkersTable(id="markers-table")

    def update_markers(self, body: dict[str, Any]) -> set[int]:
        """Show one ``markers`` message; returns the ids the daemon reports as moved."""
        self._last_body = body
        markers = body["markers"]
        bad = moved_ids(markers)
        rows = {}
        for m in markers:
            raw = dict(m, _flags=flags_of(m))
            rows[str(m["id"])] = (raw, marker_cells(m))
        table = self.query_one(MarkersTable)
        table.sync(rows)
        in_map = [m for m in markers if m.get("in_map")]
        seen = sum(1 for m in in_map if m.get("detected"))
        foreign = sum(1 for m in markers if not m.get("in_map") and m.get("detected"))
        errs = [m["error"] for m in markers if isinstance(m.get("error"), (int, float))]
        med = f"{1000 * statistics.median(errs):.1f} mm" if errs else DASH
        # This frame's suspect markers, counted from the rows shown (the same frame).
        n_suspect = sum(1 for m in markers if m["suspect"])
        evidence = ", ".join(moved_note(m) for m in markers if m["moved"])
        # Pieces by importance: the least important go first when the line is too long
        # (one line at 80 columns; a wrapped summary pushes the table down).
        pieces: list[tuple[int, str | tuple[str, str]]] = [
            (0, (f"frame {body['frame']}", "bold")),
            (0, f"map {seen}/{len(in_map)} seen"),
            (4, f"{foreign} other"),
            (2, f"LOO med {med}"),
            (0, (f"moved {len(bad)}", "bold red" if bad else "")),
            *([(1, f"({evidence})")] if evidence else []),
            (1, (f"suspect {n_suspect}", "bold yellow" if n_suspect else "")),
            (3, (table.sort_label(), "italic")),
        ]
        width = max((self.size.width or 80) - 2, 20)
        for drop in (4, 3, 2, 1):
            if sum(len(p if isinstance(p, str) else p[0]) + 3 for _, p in pieces) <= width:
                break
            pieces = [(k, p) for k, p in pieces if k < drop]
        parts: list[str | tuple[str, str]] = []
        for i, (_, p) in enumerate(pieces):
            if i:  # the evidence belongs to "moved N": a space, not a separator
                parts.append(" " if isinstance(p, str) and p.startswith("(") else " · ")
            parts.append(p)
        summary = Text.assemble(*parts, no_wrap=True, overflow="ellipsis")
        show_line(self.query_one("#markers-summary", Static), summary)
        return bad

    def on_live_table_sort_changed(self, event: LiveTable.SortChanged) -> None:
        event.stop()
        if getattr(self, "_last_body", None) is not None:
            self.update_markers(self._last_body)
