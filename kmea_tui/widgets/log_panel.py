"""Log tab: CSV logging and recording (start, stop, file, rows, size) and the daemon's events."""

from __future__ import annotations

import time
from collections import deque
from typing import Any

from rich.text import Text
from textual import on
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical
from textual.events import Resize
from textual.widgets import Button, Input, RichLog, Static

from kmea_tui.messages import ControlRequest

LEVEL_STYLES = {"DEBUG": "bright_black", "INFO": "", "WARNING": "yellow", "ERROR": "bold red",
                "CRITICAL": "bold red"}


def human_bytes(n: Any) -> str:
    if not isinstance(n, (int, float)):
        return "-"
    for unit in ("B", "kB", "MB", "GB"):
        if abs(n) < 1000 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} GB"


def clock(t: Any) -> str:
    """UTC time of day of a telemetry timestamp (s since the epoch)."""
    if not isinstance(t, (int, float)):
        return "--:--:--"
    return time.strftime("%H:%M:%S", time.gmtime(t))


def event_line(topic: str, body: dict[str, Any]) -> Text:
    level = str(body.get("level", "INFO")).upper()
    who = "event" if topic == "event" else str(body.get("logger", "log"))
    return Text.assemble((clock(body.get("t")), "bright_black"), " ",
                         (f"{level:<7}", LEVEL_STYLES.get(level, "")), " ",
                         (f"{who}: ", "cyan"), str(body.get("text", "")))


class EventLog(RichLog):
    """The events, wrapped at the width they are shown at: inside the scrollbar's gutter
    (reserved from the start, ``scrollbar-gutter: stable`` in app.tcss: a scrollbar that
    appears later would cover the ends of lines wrapped before it), and wrapped again from
    the kept entries when the terminal is resized (a line wrapped at 80 columns stays
    wrapped so in a RichLog)."""

    def __init__(self, max_lines: int = 2000, id: str | None = None) -> None:
        super().__init__(id=id, max_lines=max_lines, wrap=True, markup=False,
                         auto_scroll=True, min_width=20)
        self.entries: deque[Text] = deque(maxlen=max_lines)
        self._wrapped_at = 0

    def add(self, text: Text) -> None:
        self.entries.append(text)
        # The width given, not measured: a measure is capped by the console's width, which
        # need not follow the widget's (a log wrapped at 80 columns after a resize to 120).
        self.write(text, width=self._wrapped_at or None)

    def on_resize(self, event: Resize) -> None:
        super().on_resize(event)
        width = self.scrollable_content_region.width
        if width and self._wrapped_at and width != self._wrapped_at:
            self._wrapped_at = width
            self.clear()
            for text in self.entries:
                self.write(text, width=width)
        self._wrapped_at = width or self._wrapped_at


class LogPane(Vertical):
    BINDINGS = [Binding("l", "toggle_log", "CSV log on/off"),
                Binding("r", "toggle_record", "Record on/off")]

    def __init__(self, id: str | None = None) -> None:
        super().__init__(id=id)
        self.logging: dict[str, Any] = {}
        self.recording: dict[str, Any] = {}
        self._recent: dict[tuple[str, str], float] = {}

    def compose(self) -> ComposeResult:
        yield Static("CSV log: (no status from the daemon yet)", id="log-state")
        yield Static("recording: (no status from the daemon yet)", id="record-state")
        with Horizontal(classes="form-row"):
            yield Input(placeholder="file for the next log/recording (empty: daemon's default)",
                        id="log-path", compact=True)
            yield Button(Text("CSV log [l]"), id="log-toggle")
            yield Button(Text("Record [r]"), id="record-toggle")
        yield EventLog(id="events")

    @staticmethod
    def _state_line(what: str, s: dict[str, Any], count_label: str, count_key: str) -> Text:
        if s.get("active"):
            return Text.assemble((f"{what}: ", "bold"), ("● on", "bold green"), "  ",
                                 str(s.get("path") or "-"), "  ",
                                 f"{s.get(count_key, '-')} {count_label}", "  ",
                                 human_bytes(s.get("bytes")))
        if s.get("error"):  # stopped on its own: a write error, the free-space floor
            return Text.assemble((f"{what}: ", "bold"), ("✗ stopped", "bold red"), "  ",
                                 (str(s["error"]), "red"))
        last = f"  last: {s['path']}" if s.get("path") else ""
        return Text.assemble((f"{what}: ", "bold"), ("○ off", "bright_black"), last)

    def update_status(self, body: dict[str, Any]) -> None:
        self.logging = body.get("logging") or {}
        self.recording = body.get("recording") or {}
        # Both lines are one row high whatever they say: no layout pass needed.
        self.query_one("#log-state", Static).update(
            self._state_line("CSV log", self.logging, "rows", "rows"), layout=False)
        self.query_one("#record-state", Static).update(
            self._state_line("recording", self.recording, "frames", "frames"), layout=False)

    def add_events(self, events: list[tuple[str, dict[str, Any]]]) -> None:
        """Append events and log lines; a log line repeating an event shown within a
        second (the daemon publishes warnings both ways) is left out."""
        log = self.query_one("#events", EventLog)
        for topic, body in events:
            text, t = str(body.get("text", "")), body.get("t")
            other = "log" if topic == "event" else "event"
            seen = self._recent.get((other, text))
            if isinstance(t, (int, float)) and seen is not None and abs(t - seen) < 1.0:
                continue
            if isinstance(t, (int, float)):
                self._recent[(topic, text)] = t
                if len(self._recent) > 200:
                    self._recent.pop(next(iter(self._recent)))
            log.add(event_line(topic, body))

    def note(self, text: str, ok: bool = True) -> None:
        self.query_one("#events", EventLog).add(
            Text(("✓ " if ok else "✗ ") + text, style="green" if ok else "bold red"))

    def _path_args(self) -> dict[str, Any]:
        path = self.query_one("#log-path", Input).value.strip()
        return {"path": path} if path else {}

    @on(Button.Pressed, "#log-toggle")
    def action_toggle_log(self) -> None:
        if self.logging.get("active"):
            self.post_message(ControlRequest("log_stop", {}))
        else:
            self.post_message(ControlRequest("log_start", self._path_args()))

    @on(Button.Pressed, "#record-toggle")
    def action_toggle_record(self) -> None:
        if self.recording.get("active"):
            self.post_message(ControlRequest("record_stop", {}))
        else:
            self.post_message(ControlRequest("record_start", self._path_args()))
