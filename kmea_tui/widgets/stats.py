"""Statistics tab: the running algorithm, mean and max error, per-marker error statistics."""

from __future__ import annotations

from typing import Any

from rich.text import Text
from textual.app import ComposeResult
from textual.containers import Vertical
from textual.widgets import Static

from kmea_tui.widgets.live_table import DASH, LiveTable, fmt, show_line

COLUMNS = [
    ("id", "id"), ("n", "n"), ("rmse", "RMSE mm"), ("std", "STD mm"), ("mae", "MAE mm"),
    ("maxae", "MaxAE mm"), ("mre", "MRE %"),
]


def _sort_value(raw: dict[str, Any], col: str) -> Any:
    v = raw.get(col)
    return v if isinstance(v, (int, float)) else None


def stats_cells(s: dict[str, Any]) -> list[str | Text]:
    return [
        str(s.get("id")), str(s.get("n", DASH)),
        fmt(s.get("rmse"), ".2f", 1000.0), fmt(s.get("std"), ".2f", 1000.0),
        fmt(s.get("mae"), ".2f", 1000.0), fmt(s.get("maxae"), ".2f", 1000.0),
        fmt(s.get("mre"), ".3f"),
    ]


class StatsTable(LiveTable):
    def __init__(self, id: str | None = None) -> None:
        super().__init__(COLUMNS, sort_value=_sort_value, sort_column="id", id=id)


class StatsPane(Vertical):
    def compose(self) -> ComposeResult:
        yield Static("waiting for statistics…", id="stats-summary", classes="summary")
        yield StatsTable(id="stats-table")

    def update_stats(self, body: dict[str, Any]) -> None:
        rows = [s for s in body.get("markers", []) if isinstance(s, dict) and "id" in s]
        table = self.query_one(StatsTable)
        table.sync({str(s["id"]): (s, stats_cells(s)) for s in rows})
        show_line(self.query_one("#stats-summary", Static), Text.assemble(
            ("algorithm ", ""), (str(body.get("algorithm", DASH)), "bold"),
            f" · window {body.get('window', DASH)} frames · mean ",
            (f"{fmt(body.get('mean_error'), '.2f', 1000.0)} mm", "bold"), " · max ",
            (f"{fmt(body.get('max_error'), '.2f', 1000.0)} mm", "bold"),
            " · ", (table.sort_label() + " [s/S]", "italic"), " · reset [x]"))
