"""kmea-tui --keys: the real Textual app (Pilot) on a keyed daemon over loopback."""

from __future__ import annotations

from pathlib import Path

import pytest
from deadlines import pilot_until
from security_helpers import LiveDaemon

from kmea_tui import cli as tui_cli
from kmea_tui.app import KmeaTui
from kmea_tui.client import DaemonClient
from kmea_tui.widgets.status_bar import StatusBar
from kmead.tools import kmea_cli

_wait = pilot_until


@pytest.fixture
def keyed(tmp_path: Path):
    keys = tmp_path / "keys"
    assert kmea_cli.main(["keys", "init", str(keys)]) == 0
    assert kmea_cli.main(["keys", "add", str(keys), "wall", "--viewer"]) == 0
    (tmp_path / "site").mkdir()
    d = LiveDaemon(tmp_path / "site", sets=[f'network.keys="{keys}"'])
    yield d, keys
    d.close()


async def test_operator_ui_connects_and_controls_viewer_ui_only_watches(keyed) -> None:
    d, keys = keyed
    app = KmeaTui(DaemonClient(d.telemetry, d.control, timeout=10.0, keys=keys),
                  theme="textual-dark", ping_period=0.5)
    async with app.run_test(size=(80, 24)) as pilot:
        await _wait(pilot, lambda: app.connection_state == "connected", "operator connected")
        await _wait(pilot, lambda: app.markers_body is not None, "telemetry")
        reply = await app.client.request("set", key="filter.alpha", value=0.7)
        assert reply["ok"], reply
    assert d.daemon.cfg["filter"]["alpha"] == 0.7

    viewer = KmeaTui(DaemonClient(d.telemetry, d.control, timeout=10.0, keys=keys,
                                  client="wall"), theme="textual-dark", ping_period=0.5)
    async with viewer.run_test(size=(80, 24)) as pilot:
        await _wait(pilot, lambda: viewer.markers_body is not None, "viewer telemetry")
        # Everything live, read-only, and the status line says so.
        await _wait(pilot, lambda: viewer.connection_state == "connected", "viewer live")
        await _wait(pilot, lambda: viewer.config_loaded, "the viewer's configuration")
        assert not viewer.frozen
        await _wait(pilot, lambda: "viewer (read-only)" in str(
            viewer.query_one(StatusBar).render()), "the read-only status line")
        reply = await viewer.client.request("set", key="filter.alpha", value=0.2)
        assert reply["ok"] is False and "viewer" in reply["error"]
    assert d.daemon.cfg["filter"]["alpha"] == 0.7

    # Without keys the same UI sees nothing from a keyed daemon, and says keys may be why.
    plain = KmeaTui(DaemonClient(d.telemetry, d.control, timeout=0.5), theme="textual-dark",
                    ping_period=0.5)
    async with plain.run_test(size=(80, 24)) as pilot:
        await _wait(pilot, lambda: plain.connection_state == "disconnected", "no reply")
        assert plain.markers_body is None
        assert "--keys DIR" in str(plain.query_one(StatusBar).render())


def test_tui_with_a_missing_key_file_exits_2_with_one_line(tmp_path: Path,
                                                           capsys: pytest.CaptureFixture) -> None:
    assert tui_cli.main(["--keys", str(tmp_path), "--client", "nobody"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "server.key" in err
