"""The status line: connection state, frame rate, per-stage timings, dropped frames."""

from __future__ import annotations

from typing import Any

from rich.text import Text
from textual.widgets import Static

STATE_STYLES = {
    "connected": "bold green", "stale": "bold yellow", "disconnected": "bold red",
    "connecting": "yellow", "replay": "bold cyan", "replay end": "cyan",
    "stopped": "bold red",
}
LABELS = {"stopped": "daemon stopped"}
LIVE_STATES = ("connected", "replay", "replay end")
# Shown in this order, as long as the line has room.
STAGES = ("detect", "pose", "estimate", "loo", "filter", "robots", "output", "capture")
SHORT = {"capture": "cap", "detect": "det", "pose": "pose", "estimate": "est", "loo": "loo",
         "filter": "filt", "robots": "rob", "output": "out"}


#: s: a camera clock further off than this is an alert (the fusion node's default
#: fusion.clock_warn_s; the node's own event says when its bound is another)
CLOCK_ALERT_S = 0.05


def clock_text(offset: Any) -> str:
    """A camera's clock offset (s, positive: ahead), as ``+2 ms`` or ``+3600.0 s``."""
    if not isinstance(offset, (int, float)) or isinstance(offset, bool):
        return "-"
    return f"{offset * 1e3:+.0f} ms" if abs(offset) < 10 else f"{offset:+.1f} s"


def output_alert(status: dict[str, Any] | None) -> str:
    """A few words when the CSV log or the recording stopped on its own (a write error, the
    free-space floor: ``error`` in the status body), and a fusion node's cameras whose
    clock is off by more than :data:`CLOCK_ALERT_S`, else ""."""
    body = status or {}
    stopped = [name for key, name in (("logging", "log"), ("recording", "recording"))
               if isinstance(body.get(key), dict) and body[key].get("error")]
    words = [f"{' and '.join(stopped)} stopped (Log tab)"] if stopped else []
    for cam in body.get("inputs") or []:
        off = cam.get("clock_offset_s") if isinstance(cam, dict) else None
        if isinstance(off, (int, float)) and abs(off) > CLOCK_ALERT_S:
            words.append(f"{cam.get('label', '?')} clock {clock_text(off)}")
    return "; ".join(words)


def status_text(state: str, frame: dict[str, Any] | None, width: int = 80,
                detail: str = "", alert: str = "", read_only: bool = False,
                overlay: bool = False) -> Text:
    """One line: state ("viewer (read-only)" for a viewer key; "overlay" when saved
    settings overlay the configuration), ``alert`` (output_alert), fps, dropped frames,
    total time, then stages that fit ``width``."""
    t = Text(no_wrap=True, overflow="ellipsis")
    t.append(f"● {LABELS.get(state, state)}", STATE_STYLES.get(state, "bold"))
    if read_only:
        t.append("  viewer (read-only)", "bold cyan")
    if overlay:
        t.append("  overlay", "yellow")
    if alert:
        t.append(f"  {alert}", "bold red")
    if detail and state in ("disconnected", "stale", "connecting"):
        t.append(f" ({detail})", "bright_black")
    if frame and state not in LIVE_STATES:
        # Not live: no frame rate or timings that would look current.
        t.append(f"  last frame {frame.get('frame', '-')}", "bright_black")
        return t
    if frame:
        fps = frame.get("fps")
        t.append(f"  {fps:.1f} fps" if isinstance(fps, (int, float)) else "  - fps")
        dropped = frame.get("dropped", 0)
        t.append(f"  dropped {dropped}", "bold yellow" if dropped else "")
        if frame.get("ok") is False:
            t.append(f"  not estimated: {frame.get('reason') or '?'}", "bold red")
        timings = frame.get("timings_ms") or {}
        total = timings.get("total")
        if isinstance(total, (int, float)):
            t.append(f"  {total:.1f} ms:")
        for stage in STAGES:
            v = timings.get(stage)
            if not isinstance(v, (int, float)):
                continue
            piece = f" {SHORT[stage]} {v:.1f}"
            if len(t) + len(piece) > width - 1:
                break
            t.append(piece, "bright_black")
    return t


class StatusBar(Static):
    DEFAULT_CSS = "StatusBar { height: 1; padding: 0 1; }"

    def __init__(self, id: str | None = None) -> None:
        super().__init__("● connecting", id=id)
        self.state = "connecting"
        self.detail = ""
        self.read_only = False
        self.overlay = False  # the daemon runs with a saved overlay (status config_files)
        self.frame: dict[str, Any] | None = None
        self.alert = ""
        self._shown: Text | None = None

    def show(self, state: str, frame: dict[str, Any] | None = None, detail: str = "",
             read_only: bool | None = None) -> None:
        self.state, self.detail = state, detail
        if read_only is not None:
            self.read_only = read_only
        if frame is not None:
            self.frame = frame
        text = status_text(state, self.frame, self.size.width or 80, detail, self.alert,
                           self.read_only, self.overlay)
        if text != self._shown:  # the state is checked twice a second: mostly unchanged
            self._shown = text
            self.update(text, layout=False)

    def on_resize(self) -> None:
        self.show(self.state, None, self.detail)
