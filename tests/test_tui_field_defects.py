"""kmea-tui defects a technician met in the field (issue 28), each driven by Pilot against a
REAL kmead (subprocess on the simulated floor, loopback) or a recorded stream."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from test_tui_daemon import Daemon, wait_for
from textual.widgets import Input, TabbedContent

from kmea_tui.app import KmeaTui
from kmea_tui.client import DaemonClient
from kmea_tui.screens.quit_confirm import QuitScreen


@pytest.fixture(scope="module")
def daemon(tmp_path_factory) -> Iterator[Daemon]:
    d = Daemon(tmp_path_factory.mktemp("kmead-field"))
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


async def wait_for_file(path, text: str, timeout: float = 30.0) -> None:
    import asyncio
    import time

    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if path.exists() and text in path.read_text():
            return
        await asyncio.sleep(0.1)
    raise AssertionError(f"{text!r} not in {path} after {timeout} s")
