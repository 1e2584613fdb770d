"""kmea-tui field kit, driven by Pilot against a REAL kmead (subprocess, loopback): the
Camera tab, the stopped/stale states, the keyboard, the log on attach; and snapshots of
the Camera tab at 80x24 and 120x40 from a stored thumbnail body."""

from __future__ import annotations

import json
import os
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from deadlines import DEADLINE
from test_tui_daemon import Daemon, wait_for
from textual.widgets import Input, RichLog, TabbedContent

from kmea_tui.app import KmeaTui
from kmea_tui.client import DaemonClient, RecordingClient
from kmea_tui.messages import TelemetryBatch
from kmea_tui.widgets.camera_view import CameraPane, CameraView
from kmea_tui.widgets.robots import RobotsTable

DATA = Path(__file__).parent / "data"
# A thumbnail body as kmead sends it (kmead.net.camera_feed.camera_body on a rendered frame of
# sim:default?covered=4 at 640x480, truth outlines, marker 7 marked suspect), stored so
# the snapshot does not depend on the renderer.
THUMB = DATA / "camera_thumb.json"


@pytest.fixture(scope="module")
def daemon(tmp_path_factory) -> Iterator[Daemon]:
    # Map marker 4 covered: in view, never detected (an "expected" outline).
    d = Daemon(tmp_path_factory.mktemp("kmead-fk"), source="sim:default?covered=4")
    yield d
    d.stop()


def _app(d: Daemon) -> KmeaTui:
    return KmeaTui(DaemonClient(d.telemetry, d.control), theme="textual-dark",
                   ui_period=0.1, ping_period=0.3)


async def test_camera_tab_shows_thumbnails_only_while_shown(daemon: Daemon) -> None:
    app = _app(daemon)
    async with app.run_test(size=(80, 24)) as pilot:
        await wait_for(pilot, lambda: app.connection_state == "connected", "connected")
        pane = app.query_one(CameraPane)
        assert pane.view.frame is None  # nothing sent before anyone watches
        await pilot.press("7")
        assert app.query_one(TabbedContent).active == "camera"
        await wait_for(pilot, lambda: pane.view.frame is not None, "a thumbnail")
        f = pane.view.frame
        assert f.full_width == 640 and f.full_height == 480
        view = app.query_one(CameraView)
        # The daemon sized the thumbnail to the pane (half blocks: 2 pixels a row).
        assert f.height <= 2 * view.size.height and f.width <= view.size.width
        assert 4 in {m.id for m in f.markers if m.kind == "expected"}
        caption = str(app.query_one("#camera-caption").render())
        assert "seen" in caption and "expected unseen" in caption and "focus" in caption
        svg = app.export_screenshot()
        assert "(4)" in svg  # the covered marker's label
        # Snapshot key: a PNG in the daemon's data directory.
        before = set(daemon.cwd.glob("snapshot-*.png"))
        await pilot.press("o")
        await wait_for(pilot, lambda: set(daemon.cwd.glob("snapshot-*.png")) - before,
                       "a snapshot file")
        # b switches to braille; another tab ends the lease renewals.
        await pilot.press("b")
        assert view.braille
        await pilot.press("1")
        await wait_for(pilot, lambda: not [w for w in app.workers
                                           if w.group == "camera" and w.is_running],
                       "the camera lease renewals to end")


async def test_stale_when_silent_then_live_again(daemon: Daemon) -> None:
    app = _app(daemon)
    async with app.run_test(size=(80, 24)) as pilot:
        await wait_for(pilot, lambda: app.connection_state == "connected", "connected")
        await pilot.press("2")
        table = app.query_one(RobotsTable)
        await wait_for(pilot, lambda: "ok" in _cells(table), "a robot ok")
        os.kill(daemon.proc.pid, signal.SIGSTOP)  # a hung daemon: no telemetry, no replies
        try:
            await wait_for(pilot, lambda: app.frozen, "the UI to freeze the data", 15)
            assert app.connection_state in ("stale", "disconnected")
            status = str(app.query_one("#status").render())
            assert "fps" not in status and "last frame" in status
            await wait_for(pilot, lambda: "ok" not in _cells(table), "no robot ok")
            assert "unknown" in _cells(table)
            assert app.screen.has_class("-frozen")
            assert "NOT LIVE" in str(app.query_one("#robots-summary").render())
        finally:
            os.kill(daemon.proc.pid, signal.SIGCONT)
        await wait_for(pilot, lambda: app.connection_state == "connected", "live again")
        await wait_for(pilot, lambda: "ok" in _cells(table), "robots ok again")
        assert not app.screen.has_class("-frozen")


def _cells(table: RobotsTable) -> list[str]:
    out = []
    for row in range(table.row_count):
        out += [str(c) for c in table.get_row_at(row)]
    return out


async def test_keyboard_escape_q_and_a_rejected_value(daemon: Daemon) -> None:
    app = _app(daemon)
    async with app.run_test(size=(80, 24)) as pilot:
        await wait_for(pilot, lambda: app.config_loaded, "configuration")
        await wait_for(pilot, lambda: "^q" in app.export_screenshot(), "^q Quit in the footer")
        await pilot.press("5")
        alpha = app.query_one("#filter-alpha", Input)
        current = alpha.value
        alpha.focus()
        alpha.value = ""
        await pilot.press("2", "enter")  # alpha must be in [0.001, 1]: the daemon refuses
        await wait_for(pilot, lambda: "must be in [0.001, 1]" in str(
            app.query_one("#config-status").render()), "the daemon's refusal")
        assert alpha.value == current  # the field shows the value in force again
        assert not alpha.has_focus  # Enter gave the keys back to the tab
        alpha.focus()
        await pilot.press("end")  # focus selects the text: typing would replace it
        # q, digits typed into the field are text ...
        await pilot.press("q", "1")
        assert alpha.value == current + "q1" and app.query_one(TabbedContent).active == "config"
        alpha.value = current
        # ... until Escape leaves it: then 1 changes tab and q quits.
        await pilot.press("escape")
        assert not alpha.has_focus
        await pilot.press("1")
        assert app.query_one(TabbedContent).active == "markers"
        await pilot.press("q")
        await pilot.pause(0.2)
    assert app.return_code == 0 and not app.is_running


async def test_log_tab_shows_the_daemons_log_on_attach(daemon: Daemon) -> None:
    app = _app(daemon)
    async with app.run_test(size=(80, 24)) as pilot:
        await pilot.press("6")
        events = app.query_one("#events", RichLog)
        # "running: source ..." was logged at the daemon's start, long before this UI.
        def shown() -> str:  # long lines wrap: join them
            return " ".join("".join(s.text for s in line).strip() for line in events.lines)

        await wait_for(pilot, lambda: "before this UI attached" in shown()
                       and "running: source" in shown(), "the daemon's log")


# ---------------------------------------------------------------- snapshots (no daemon)
def _camera_app() -> KmeaTui:
    return KmeaTui(RecordingClient(DATA / "telemetry_sim.jsonl"), theme="textual-dark")


async def _show_thumbnail(pilot) -> None:
    app = pilot.app
    end = time.monotonic() + DEADLINE  # a loaded machine replays slowly: wait, do not count
    while time.monotonic() < end and not (app.replay_done and app.config_loaded):
        await pilot.pause(0.01)
    await pilot.press("7")
    body = json.loads(THUMB.read_text())
    app.post_message(TelemetryBatch({"camera": body}))
    await pilot.pause(0.2)


@pytest.mark.parametrize("size", [(80, 24), (120, 40)], ids=["80x24", "120x40"])
def test_camera_tab_snapshot(snap_compare, size: tuple[int, int]) -> None:
    assert snap_compare(_camera_app(), terminal_size=size, run_before=_show_thumbnail)


def test_thumbnail_fixture_is_a_valid_body() -> None:
    from kmea_tui.widgets.camera_view import CameraFrame

    f = CameraFrame.from_body(json.loads(THUMB.read_text()))
    assert (f.width, f.height, f.full_width, f.full_height) == (160, 120, 640, 480)
    assert {m.kind for m in f.markers} == {"detected", "suspect", "expected"}
