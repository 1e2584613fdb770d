"""Snapshots of every kmea-tui tab at 80x24 and 120x40 from a recorded telemetry stream.

The recording is replayed all at once (RecordingClient, not realtime), so the UI shows its
final state; nothing on screen depends on the wall clock (ages, times and rates all come
from the recording). Update after a deliberate UI change with
``pytest tests/test_tui_snapshots.py --snapshot-update`` and look at the SVGs.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from deadlines import DEADLINE

from kmea_tui.app import TABS, KmeaTui
from kmea_tui.client import RecordingClient

RECORDING = Path(__file__).parent / "data" / "telemetry_sim.jsonl"
KEYS = {tab: str(i + 1) for i, (tab, _) in enumerate(TABS)}


async def _until_replayed(pilot) -> None:
    app = pilot.app
    end = time.monotonic() + DEADLINE  # a loaded machine replays slowly: wait, do not count
    while time.monotonic() < end and not (app.replay_done and app.config_loaded):
        await pilot.pause(0.01)
    assert app.replay_done and app.config_loaded


def _app(theme: str = "textual-dark") -> KmeaTui:
    return KmeaTui(RecordingClient(RECORDING), theme=theme)


@pytest.mark.parametrize("size", [(80, 24), (120, 40)], ids=["80x24", "120x40"])
@pytest.mark.parametrize("tab", [t for t, _ in TABS])
def test_tab_snapshot(snap_compare, tab: str, size: tuple[int, int]) -> None:
    assert snap_compare(_app(), press=[KEYS[tab]], terminal_size=size,
                        run_before=_until_replayed)


def test_ansi_theme_snapshot(snap_compare) -> None:
    """The 16-colour theme used on terminals without 256 colours."""
    assert snap_compare(_app("ansi-dark"), press=["1"], terminal_size=(80, 24),
                        run_before=_until_replayed)
