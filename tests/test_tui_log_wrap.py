"""The Log tab wraps its lines inside what is shown: never under the scrollbar at 80x24, and
again at the new width after a resize (the real app, driven by its Pilot, on a recording)."""

from __future__ import annotations

from pathlib import Path

from kmea_tui.app import KmeaTui
from kmea_tui.client import RecordingClient
from kmea_tui.widgets.log_panel import EventLog, LogPane

DATA = Path(__file__).parent / "data"
# With the time, level and source (28 columns): wider than 80 columns, narrower than 120.
LONG = "robot amr1 not seen for 0.5 s: stale (valid=0 sent): its frames stopped"


def _rows(log: EventLog) -> list[str]:
    return ["".join(s.text for s in line) for line in log.lines]


async def test_events_wrap_inside_the_gutter_and_again_after_a_resize() -> None:
    app = KmeaTui(RecordingClient(DATA / "telemetry_sim.jsonl"), theme="textual-dark")
    async with app.run_test(size=(80, 24)) as pilot:
        await pilot.press("6")
        pane = app.query_one(LogPane)
        log = app.query_one("#events", EventLog)
        for i in range(40):  # enough lines for a scrollbar
            pane.add_events([("event", {"level": "warning", "t": 1.7e9 + i,
                                        "text": f"{i}: {LONG}"})])
        await pilot.pause()
        width = log.scrollable_content_region.width
        assert 0 < width < 80
        rows = _rows(log)
        assert max(len(r.rstrip()) for r in rows) <= width
        joined = " ".join(r.strip() for r in rows)
        assert f"39: {LONG}" in joined  # nothing lost under the scrollbar
        narrow = len(rows)
        await pilot.resize_terminal(120, 40)
        await pilot.pause()
        wide_width = log.scrollable_content_region.width
        assert wide_width > width
        rows = _rows(log)
        assert len(rows) < narrow  # wrapped again at the new width
        assert max(len(r.rstrip()) for r in rows) > width
        assert max(len(r.rstrip()) for r in rows) <= wide_width
        assert f"39: {LONG}" in " ".join(r.strip() for r in rows)
