"""kmea-tui defects a technician met in the field (issue 28), each driven by Pilot against a
REAL kmead (subprocess on the simulated floor, loopback) or a recorded stream."""

from __future__ import annotations

import os
import signal
import socket
from collections.abc import Iterator
from pathlib import Path

import pytest
from deadlines import DEADLINE
from test_tui_daemon import Daemon, wait_for
from textual.widgets import Button, Input, TabbedContent

from kmea_tui.app import KmeaTui
from kmea_tui.client import DaemonClient, RecordingClient
from kmea_tui.screens.quit_confirm import QuitScreen
from kmea_tui.widgets.markers import COLUMNS as MARKER_COLUMNS
from kmea_tui.widgets.markers import MarkersTable
from kmea_tui.widgets.robots import RobotsTable


@pytest.fixture(scope="module")
def ports() -> Iterator[tuple[int, int]]:
    """(a UDP port nobody listens on, a port this test listens on)."""
    closed = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    closed.bind(("127.0.0.1", 0))
    port = closed.getsockname()[1]
    closed.close()
    listener = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    listener.bind(("127.0.0.1", 0))
    yield port, listener.getsockname()[1]
    listener.close()


@pytest.fixture(scope="module")
def daemon(tmp_path_factory, ports) -> Iterator[Daemon]:
    # The simulator's two robots: amr1 sends where nothing listens (like the default
    # destinations on a first start), amr2 to a listener.
    robots = ", ".join(
        f'{{name="{n}", markers={m}, height=0.2, destinations=["udp:127.0.0.1:{p}"]}}'
        for n, m, p in (("amr1", "[40, 41]", ports[0]), ("amr2", "[42]", ports[1])))
    d = Daemon(tmp_path_factory.mktemp("kmead-field"),
               extra=("--algorithm", "kmea", "--set", f"robots=[{robots}]"))
    yield d
    d.stop()


def _app(d: Daemon) -> KmeaTui:
    return KmeaTui(DaemonClient(d.telemetry, d.control), theme="textual-dark",
                   ui_period=0.1, ping_period=0.3)


async def _set_alpha(pilot, app: KmeaTui, text: str) -> Input:
    """Config tab: type ``text`` into filter alpha and press Enter."""
    await wait_for(pilot, lambda: app.config_loaded, "configuration")
    await pilot.press("5")
    alpha = app.query_one("#filter-alpha", Input)
    alpha.focus()
    alpha.value = ""
    await pilot.press(*text, "enter")
    return alpha


def _alpha(app: KmeaTui) -> object:
    return app.query_one("#config-pane").config.get("filter", {}).get("alpha")


async def test_enter_applies_the_value_and_gives_the_keys_back_to_the_tab(daemon) -> None:
    app = _app(daemon)
    async with app.run_test(size=(80, 24)) as pilot:
        alpha = await _set_alpha(pilot, app, "0.6")
        assert not alpha.has_focus
        await pilot.press("6")  # a tab key again, not a digit typed into the field
        assert app.query_one(TabbedContent).active == "log"
        await wait_for(pilot, lambda: _alpha(app) == 0.6, "filter.alpha = 0.6 applied")
        assert alpha.value == "0.6"


async def test_quit_with_unsaved_live_changes_asks_once(daemon) -> None:
    # Nothing changed: q quits at once.
    app = _app(daemon)
    async with app.run_test(size=(80, 24)) as pilot:
        await wait_for(pilot, lambda: app.config_loaded, "configuration")
        await pilot.press("q")
        await pilot.pause(0.2)
    assert not app.is_running

    # A live change: q asks; Escape cancels; q asks again and q once more quits.
    app = _app(daemon)
    async with app.run_test(size=(80, 24)) as pilot:
        await _set_alpha(pilot, app, "0.4")
        await wait_for(pilot, lambda: _alpha(app) == 0.4, "filter.alpha = 0.4 applied")
        await pilot.press("q")
        await wait_for(pilot, lambda: isinstance(app.screen, QuitScreen), "the question")
        assert "filter.alpha" in str(app.screen.query_one("#quit-keys").render())
        # Each answer's key is on its button, whole (a label is not read as markup).
        labels = [str(b.label) for b in app.screen.query(Button)]
        assert labels == ["Quit anyway [q]", "Save and quit [s]", "Cancel [Esc]"]
        assert all(b.content_size.width >= len(str(b.label)) for b in app.screen.query(Button))
        await pilot.press("escape")
        await wait_for(pilot, lambda: not isinstance(app.screen, QuitScreen), "cancelled")
        assert app.is_running
        await pilot.press("q")
        await wait_for(pilot, lambda: isinstance(app.screen, QuitScreen), "asked again")
        await pilot.press("q")
        await pilot.pause(0.2)
    assert not app.is_running

    # Save and quit: the daemon writes its overlay, then the UI quits.
    overlay = daemon.cwd / "config-home" / "kmead" / "kmead.local.toml"
    app = _app(daemon)
    async with app.run_test(size=(80, 24)) as pilot:
        await _set_alpha(pilot, app, "0.3")
        await wait_for(pilot, lambda: _alpha(app) == 0.3, "filter.alpha = 0.3 applied")
        await pilot.press("q")
        await wait_for(pilot, lambda: isinstance(app.screen, QuitScreen), "the question")
        await pilot.press("s")
        await wait_for(pilot, lambda: not app.is_running, "quit after the save")
    # The change is on trial for 20 frames; the daemon saves it once the trial passes.
    await wait_for_file(overlay, "alpha = 0.3")


async def wait_for_file(path, text: str, timeout: float = DEADLINE) -> None:
    import asyncio
    import time

    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if path.exists() and text in path.read_text():
            return
        await asyncio.sleep(0.1)
    raise AssertionError(f"{text!r} not in {path} after {timeout} s")


RECORDING = Path(__file__).parent / "data" / "telemetry_sim.jsonl"


async def _replayed(app: KmeaTui, pilot) -> None:
    await wait_for(pilot, lambda: app.replay_done and app.config_loaded, "the replay")


@pytest.mark.parametrize("presses", [["s"] * 8 + ["S"], ["S"], ["s", "s"]],
                         ids=["LOO-reversed", "id-reversed", "det"])
async def test_sort_indicator_stays_visible_at_80x24(presses: list[str]) -> None:
    app = KmeaTui(RecordingClient(RECORDING), theme="textual-dark")
    async with app.run_test(size=(80, 24)) as pilot:
        await _replayed(app, pilot)
        table = app.query_one(MarkersTable)
        await pilot.press(*presses)
        arrow = "▼" if table.sort_reverse else "▲"
        # What is on screen (the header line as drawn, cropped to the terminal) shows
        # which column sorts, and which way.
        header = table.render_line(0).text
        label = dict(MARKER_COLUMNS)[table.sort_column]
        at = header.index(arrow)
        assert at < 80 and label[:-1] in header[:at]
        screen = app.export_screenshot()
        assert arrow in screen


def _row_line(table: RobotsTable, name: str) -> str:
    """Robot ``name``'s row as drawn on screen (cropped to the terminal's width)."""
    index = [table.row_key_at(i) for i in range(table.row_count)].index(name)
    return table.render_line(index + 1 - int(table.scroll_y)).text


def _cell(table: RobotsTable, name: str, column: str) -> str:
    return str(table.get_cell(name, column)) if name in table.rows else ""


async def test_loopback_destinations_readable_at_80x24() -> None:
    app = KmeaTui(RecordingClient(RECORDING), theme="textual-dark")
    async with app.run_test(size=(80, 24)) as pilot:
        await _replayed(app, pilot)
        await pilot.press("2")
        table = app.query_one(RobotsTable)
        await wait_for(pilot, lambda: table.row_count == 2, "two robots")
        # The recording's destinations are udp:127.0.0.1:9001 and :9002; the port is
        # what tells them apart, whole on screen.
        for name, port in (("amr1", 9001), ("amr2", 9002)):
            line = _row_line(table, name)
            assert line.rstrip().endswith(f"  :{port}"), line  # not 127.0.0.1:90...


async def test_a_destination_nobody_listens_on_says_so(daemon, ports) -> None:
    closed, listening = ports
    app = _app(daemon)
    async with app.run_test(size=(80, 24)) as pilot:
        await wait_for(pilot, lambda: app.connection_state == "connected", "connected")
        await pilot.press("2")
        table = app.query_one(RobotsTable)
        # Refusals are explained, not shown as send failures (✗N in the sent column).
        await wait_for(pilot, lambda: _cell(table, "amr1", "sent") == "no listener",
                       "amr1: no listener")
        line = _row_line(table, "amr1")
        assert "no listener" in line and line.rstrip().endswith(f"  :{closed}"), line
        # The robot whose receiver listens: its port only, no warning.
        await wait_for(pilot, lambda: _cell(table, "amr2", "sent") not in ("", "0"),
                       "amr2 sending")
        assert _cell(table, "amr2", "destinations") == f":{listening}"
        assert "✗" not in _cell(table, "amr2", "sent")


def _age(table: RobotsTable, name: str) -> float:
    try:
        return float(_cell(table, name, "age_s"))
    except ValueError:
        return -1.0


async def test_age_grows_while_the_daemon_is_silent(daemon) -> None:
    app = _app(daemon)
    async with app.run_test(size=(80, 24)) as pilot:
        await wait_for(pilot, lambda: app.connection_state == "connected", "connected")
        await pilot.press("2")
        table = app.query_one(RobotsTable)
        await wait_for(pilot, lambda: _cell(table, "amr2", "state") == "ok", "amr2 ok")
        os.kill(daemon.proc.pid, signal.SIGSTOP)  # a hung daemon: nothing arrives
        try:
            await wait_for(pilot, lambda: app.frozen, "the data frozen")
            first = _age(table, "amr2")
            # The age of the last known fix keeps growing on the local clock.
            await wait_for(pilot, lambda: _age(table, "amr2") >= first + 2.0,
                           "amr2's age to grow by 2 s")
            assert _cell(table, "amr2", "state") == "unknown"
        finally:
            os.kill(daemon.proc.pid, signal.SIGCONT)
        await wait_for(pilot, lambda: app.connection_state == "connected", "live again")
        await wait_for(pilot, lambda: _cell(table, "amr2", "state") == "ok"
                       and _age(table, "amr2") < 1.0, "a fresh fix again")


def test_kmead_with_its_ui_says_it_is_starting_before_the_floor_is_built(tmp_path) -> None:
    """``kmead --source sim`` on a terminal: the first thing on it says what is loading (the
    simulated floor takes 15-20 s), then the UI takes over; q quits."""
    import fcntl
    import pty
    import struct
    import subprocess
    import sys
    import termios
    import time

    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 80, 0, 0))
    env = {**os.environ, "XDG_CONFIG_HOME": str(tmp_path / "config-home"),
           "TERM": "xterm-256color"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "kmead.cli", "--source", "sim", "--free-ports",
         "--set", "source.width=640", "--set", "source.height=480",
         "--set", "source.fps=5"],
        stdin=slave, stdout=slave, stderr=slave, cwd=tmp_path, env=env, close_fds=True)
    os.close(slave)
    out = b""

    def read_until(pattern: bytes, timeout: float) -> bool:
        nonlocal out
        end = time.monotonic() + timeout
        while time.monotonic() < end and pattern not in out:
            import select

            if select.select([master], [], [], 0.2)[0]:
                try:
                    out += os.read(master, 65536)
                except OSError:  # the child closed the terminal
                    return pattern in out
        return pattern in out

    try:
        assert read_until(b"kmead: starting (loading the map, building the simulated floor",
                          60), out[-2000:]
        # The line comes before anything of the UI (which needs the built daemon).
        first_ui = out.find(b"\x1b[?1049h")  # the UI's alternate screen
        assert first_ui == -1 or out.index(b"kmead: starting") < first_ui
        assert read_until(b"connected", 90), out[-2000:]
        # A key typed while a loaded machine is still drawing the first screens can be
        # read before the app listens: press q again until it quits (a second q also
        # answers a quit question), with a generous deadline.
        end = time.monotonic() + 120
        while proc.poll() is None and time.monotonic() < end:
            os.write(master, b"q")
            read_until(b"\x00never", 3.0)  # drain the pty (the UI blocks on a full one)
        assert proc.wait(timeout=DEADLINE) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        os.close(master)
