"""The terminal UI on a fusion node (the real app, Pilot, real sockets): it opens on Robots,
says what a fusion node does not have (markers, statistics, camera) instead of waiting
forever, asks for no camera, and draws the floor of the map the node was given."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest
from deadlines import JOIN, pilot_until

pytest.importorskip("zenoh", reason="the zenoh extra is not installed "
                                    "(pip install 'kmea[zenoh]')")

from zenoh_helpers import free_port, zenoh_sets

from kmea.maps.files import save_map_toml
from kmea.sim.scenes import get_scene
from kmea_tui.app import KmeaTui
from kmea_tui.client import DaemonClient
from kmea_tui.widgets.floor_map import FloorMap
from kmead.config.layers import load_config
from kmead.fusion.node import FusionNode

_wait = pilot_until


async def test_fusion_node_ui_opens_on_robots_and_draws_its_map(tmp_path: Path) -> None:
    wide = tmp_path / "wide.toml"
    save_map_toml(get_scene("wide").effective_map(), wide)
    cfg = load_config(None, ['network.telemetry="tcp://127.0.0.1:*"',
                             'network.control="tcp://127.0.0.1:*"', 'log.level="warning"',
                             "network.status_period_s=0.5", f'map.file="{wide}"',
                             *zenoh_sets(listen=free_port())])
    # No camera on its site: the node runs, with nothing to fuse.
    node = FusionNode(cfg)
    assert node.telemetry is not None and node.control is not None
    tn = threading.Thread(target=node.run, daemon=True)
    tn.start()
    app = KmeaTui(DaemonClient(node.telemetry.bound, node.control.bound, timeout=2.0),
                  theme="textual-dark", ping_period=0.5)
    try:
        async with app.run_test(size=(80, 24)) as pilot:
            await _wait(pilot, lambda: app.fusion_node, "the fusion node's status")
            await _wait(pilot, lambda: app.query_one("TabbedContent").active == "robots",
                        "the Robots tab")
            summary = str(app.query_one("#markers-summary").render())
            assert "a fusion node has no markers" in summary
            assert "no marker statistics" in str(app.query_one("#stats-summary").render())
            await pilot.press("3")  # Statistics: no statistics to reset on a fusion node
            await _wait(pilot, lambda: app.query_one("TabbedContent").active == "stats",
                        "the Statistics tab")
            assert app.check_action("reset_stats", ()) is False
            await pilot.press("7")
            await pilot.pause(0.5)
            caption = str(app.query_one("#camera-caption").render())
            assert "not available on a fusion node" in caption
            # The node's map: the wide floor's outline (x up to 2.395 m), not the built-in,
            # with its markers' ids (from the status: a node has no markers telemetry).
            await pilot.press("4")
            fmap = app.query_one(FloorMap)
            await _wait(pilot, lambda: len(fmap.data.markers) > 60, "the map's markers")
            x0, x1, _, _ = fmap.extent()
            assert x0 < -0.69 and x1 > 2.39
            drawn = "\n".join("".join(s.text for s in line) for line in fmap._render_strips())
            assert sum(tok.isdigit() for tok in drawn.split()) >= 10  # marker ids drawn
            # No camera request was refused (the UI never asks a fusion node for one), and
            # a direct one gets a reason, not an internal error.
            # The Configuration tab offers nothing a fusion node does not have.
            await pilot.press("5")
            await pilot.pause(0.3)
            hidden = [w for w in app.query(".camera-only")]
            assert hidden and not any(w.display for w in hidden)
            assert not app.query_one("#algorithm").parent.display  # its row is hidden
            assert "a fusion node" in str(app.query_one("#save-note").render())
            reply = await app.client.request("camera_watch", width=80, height=40)
            assert reply["ok"] is False and "fusion node" in reply["error"]
            assert (await app.client.request("get_log", limit=5))["ok"] is True
    finally:
        node.stop()
        tn.join(timeout=JOIN)
        node.close()


def test_fusion_node_status_names_its_map(tmp_path: Path) -> None:
    cfg = load_config(None, ['network.telemetry="tcp://127.0.0.1:*"', 'network.control=""',
                             *zenoh_sets(listen=free_port())])
    node = FusionNode(cfg)
    try:
        m = node.status()["map"]
        assert m["name"] == "RobotAtFactory 4.0" and m["n"] == 49
        assert m["extent"] == [-0.695, 0.695, -0.355, 0.355]
    finally:
        node.close()
