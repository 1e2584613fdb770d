"""The Markers tab shows where the estimator put each marker of unknown plane (the daemon's
``markers[].plane``), driven by Pilot against a REAL kmead on the simulated floor.

No robot is configured (``robots=[]``), so the robots' markers 40-42, 20 cm above the floor
on their top plates, are neither in the map nor on a configured robot: their plane is
unknown. With ``estimator.unknown_plane = "floor"`` the daemon puts them on the floor; with
the default ``"auto"`` (corner-pnp's likelihood-ratio test) they are estimated free, since
20 cm is far beyond what their corners allow on the floor. Map markers show a dash.
"""

from __future__ import annotations

import pytest
from test_tui_daemon import Daemon, _app, wait_for

from kmea_tui.widgets.live_table import DASH
from kmea_tui.widgets.markers import MarkersTable

ROBOT_MARKERS = ("40", "41", "42")


@pytest.mark.parametrize(("mode", "want"), [("auto", "free"), ("floor", "floor")])
async def test_markers_tab_shows_the_plane_choice(tmp_path, mode: str, want: str) -> None:
    d = Daemon(tmp_path, extra=("--set", "robots=[]",
                                "--set", f'estimator.unknown_plane="{mode}"'))
    try:
        app = _app(d)
        async with app.run_test(size=(120, 40)) as pilot:
            markers = app.query_one(MarkersTable)

            def robots_placed() -> bool:
                raw = markers.raw
                return all(i in raw and raw[i].get("detected") and raw[i].get("plane")
                           for i in ROBOT_MARKERS)

            await wait_for(pilot, robots_placed, "the robot markers with a plane choice")
            for i in ROBOT_MARKERS:
                assert markers.raw[i]["plane"] == want
                assert str(markers.get_cell(i, "plane")) == want
            # A map marker has a known plane: nothing to choose, a dash.
            assert markers.raw["13"].get("plane") is None
            assert str(markers.get_cell("13", "plane")) == DASH
    finally:
        d.stop()
