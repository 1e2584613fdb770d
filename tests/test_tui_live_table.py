"""The live tables and the map redraw only what changed (issue 14: the UI's CPU).

The real app replays ``tests/data/telemetry_sim.jsonl`` at once, then one more markers
message is posted with a single value changed: that cell shows the new value and exactly its
line is drawn again (``LiveTable.lines_rendered`` counts the lines Textual asked for).
"""

from __future__ import annotations

import copy
import json
import time
from pathlib import Path
from typing import Any

from deadlines import DEADLINE
from rich.style import Style
from rich.text import Text

from kmea_tui.app import KmeaTui
from kmea_tui.client import RecordingClient
from kmea_tui.messages import TelemetryBatch
from kmea_tui.widgets.floor_map import FloorMap, MapData, MapPane
from kmea_tui.widgets.markers import MarkersTable

RECORDING = Path(__file__).parent / "data" / "telemetry_sim.jsonl"


def _last(topic: str) -> dict[str, Any]:
    records = [json.loads(line) for line in RECORDING.read_text().splitlines()[1:]]
    return copy.deepcopy([r["body"] for r in records if r["topic"] == topic][-1])


async def _replayed(app: KmeaTui, pilot: Any) -> None:
    end = time.monotonic() + DEADLINE  # a loaded machine replays slowly: wait, do not count
    while time.monotonic() < end and not (app.replay_done and app.config_loaded):
        await pilot.pause(0.01)
    assert app.replay_done and app.config_loaded
    await pilot.pause(0.1)


async def _post_markers(app: KmeaTui, pilot: Any, body: dict[str, Any]) -> None:
    app.post_message(TelemetryBatch({"markers": body}))
    end = time.monotonic() + DEADLINE
    while time.monotonic() < end and app.markers_body is not body:
        await pilot.pause(0.01)
    await pilot.pause(0.1)  # the screen's next refresh


def _line_text(table: MarkersTable, y: int) -> str:
    return "".join(s.text for s in table.render_line(y))


async def test_one_changed_value_redraws_exactly_its_cell_and_line() -> None:
    app = KmeaTui(RecordingClient(RECORDING), theme="textual-dark")
    async with app.run_test(size=(120, 40)) as pilot:
        await _replayed(app, pilot)
        table = app.query_one(MarkersTable)
        assert table.row_count >= 30 and table.sort_column == "id"
        body = _last("markers")
        marker = next(m for m in body["markers"] if m.get("detected") and m.get("in_map")
                      and not m.get("moved") and not m.get("suspect"))
        key = str(marker["id"])
        y = 1 + [table.row_key_at(i) for i in range(table.row_count)].index(key)
        shown_before = {i: _line_text(table, i) for i in range(table.size.height)}
        cells_before = {k: table.rows[k].cells for k in table.rows}
        row_before, rendered = table.rows[key], table.lines_rendered

        marker["x"] = 0.4321
        body["frame"] += 1
        await _post_markers(app, pilot, body)

        # The cell shows the new value, in the same row object, nothing else changed ...
        assert str(table.get_cell(key, "x")) == "0.432"
        assert table.rows[key] is row_before
        changed = {k for k in table.rows if table.rows[k].cells != cells_before[k]}
        assert changed == {key}
        # ... and Textual drew that one line again, not the table.
        assert table.lines_rendered - rendered == 1
        shown = {i: _line_text(table, i) for i in range(table.size.height)}
        assert {i for i in shown if shown[i] != shown_before[i]} == {y}
        assert " 0.432 " in shown[y] and f" {key} " in shown[y]
        # The screen itself (the compositor's output) has it.
        assert "0.432" in app.export_screenshot()


async def test_cursor_sorting_by_header_click_and_flag_colours() -> None:
    app = KmeaTui(RecordingClient(RECORDING), theme="textual-dark")
    async with app.run_test(size=(120, 40)) as pilot:
        await _replayed(app, pilot)
        table = app.query_one(MarkersTable)
        assert table.has_focus and table.cursor_row == 0
        # The cursor moves down: its old and new lines are drawn again, only those.
        rendered = table.lines_rendered
        await pilot.press("down")
        await pilot.pause(0.1)
        assert table.cursor_row == 1 and table.lines_rendered - rendered == 2
        cursor_bg = table.get_component_rich_style("live-table--cursor").bgcolor
        assert cursor_bg is not None
        # (the cells; the blank right of the last column is the table's background)
        assert all(s.style.bgcolor == cursor_bg for s in table.render_line(2) if s.text.strip())
        assert all(s.style.bgcolor != cursor_bg for s in table.render_line(1) if s.text.strip())

        # A moved marker's row is bold red (7 moved 2 cm in this recording).
        row7 = 1 + [table.row_key_at(i) for i in range(table.row_count)].index("7")
        id_cell = next(s for s in table.render_line(row7) if s.text.strip() == "7")
        assert id_cell.style.color == Style.parse("bold red").color and id_cell.style.bold

        # A click on the "LOO mm" header sorts by the leave-one-out error; again: reversed.
        header = _line_text(table, 0)
        x = header.index("LOO mm")
        await pilot.click(MarkersTable, offset=(x, 0))
        await pilot.pause(0.05)
        assert table.sort_column == "error" and not table.sort_reverse
        errors = [table.raw[table.row_key_at(i)].get("error") for i in range(table.row_count)]
        known = [e for e in errors if isinstance(e, (int, float))]
        assert known == sorted(known) and errors[:len(known)] == known  # missing ones last
        await pilot.click(MarkersTable, offset=(x, 0))
        await pilot.pause(0.05)
        assert table.sort_reverse
        assert "sort LOO mm▼" in str(app.query_one("#markers-summary").render())


async def test_rows_come_and_go_in_place() -> None:
    app = KmeaTui(RecordingClient(RECORDING), theme="textual-dark")
    async with app.run_test(size=(80, 24)) as pilot:
        await _replayed(app, pilot)
        table = app.query_one(MarkersTable)
        n, removed = table.row_count, table.rows_removed
        body = _last("markers")
        gone = body["markers"].pop(0)
        await _post_markers(app, pilot, body)
        assert table.row_count == n - 1 and table.rows_removed == removed + 1
        assert str(gone["id"]) not in table.rows
        assert _line_text(table, 1).split()[0] == str(body["markers"][0]["id"])
        body = copy.deepcopy(body)
        body["markers"].append(dict(gone, id=49, in_map=False))
        await _post_markers(app, pilot, body)
        assert table.row_count == n and str(table.get_cell("49", "map")) == "no"
        # A cell that changes colour only (same text) is drawn again too (rich Texts with
        # the same text compare equal whatever their style).
        rows = {k: (r.raw, list(r.cells)) for k, r in table.rows.items()}
        key = table.row_key_at(0)
        for colour in ("magenta", "cyan"):
            rows[key][1][0] = Text(key, style=f"bold {colour}")
            rendered = table.lines_rendered
            table.sync(rows)
            await pilot.pause(0.1)
            assert table.lines_rendered - rendered == 1
            first = next(s for s in table.render_line(1) if s.text.strip() == key)
            assert first.style.color == Style.parse(colour).color


async def test_map_redraws_only_the_lines_a_robot_moved_on() -> None:
    app = KmeaTui(RecordingClient(RECORDING), theme="textual-dark")
    async with app.run_test(size=(120, 40)) as pilot:
        await _replayed(app, pilot)
        await pilot.press("4")
        await pilot.pause(0.1)
        fm, pane = app.query_one(FloorMap), app.query_one(MapPane)
        drawn: list[int] = []
        original = fm.render_line

        def counting(y: int) -> Any:
            drawn.append(y)
            return original(y)

        markers = app.markers_body["markers"]  # type: ignore[index]
        robots = copy.deepcopy(app.robots_body["robots"])  # type: ignore[index]
        pane.set_data(MapData(markers=markers, robots=robots, moved={7}))
        await pilot.pause(0.1)
        before = [s.text for s in fm._strips or []]
        assert len(before) == fm.size.height > 20
        fm.render_line = counting  # type: ignore[method-assign]
        robot = next(r for r in robots if isinstance(r.get("x"), float))
        robot["y"] += 0.1  # about 3 text rows up at 120x40
        pane.set_data(MapData(markers=markers, robots=robots, moved={7}))
        await pilot.pause(0.1)
        after = [s.text for s in fm._strips or []]
        changed = {y for y, (a, b) in enumerate(zip(before, after, strict=True)) if a != b}
        # The robot's arrow, name and heading moved: those lines, not the whole map.
        assert changed and set(drawn) == changed
        assert len(changed) < fm.size.height // 3
