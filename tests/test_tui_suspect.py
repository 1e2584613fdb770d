"""kmea-tui shows the daemon's ``suspect`` markers (protocol.md: ``markers[].suspect``).

The stream is ``tests/data/telemetry_sim.jsonl``, recorded from a real ``kmead --source
"sim:misplaced?robots=true"`` by ``scripts/record_telemetry.py``: in frame 32 robot amr2's
plate covers a corner of floor marker 25 (suspect: estimated, not a reference, no LOO
error). ``test_suspect_ids_are_the_detectors`` checks the recorded flags against real OpenCV
detection of the rendered frames.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
from deadlines import DEADLINE
from rich.style import Style

from kmea_tui.app import KmeaTui
from kmea_tui.client import RecordingClient
from kmea_tui.messages import TelemetryBatch
from kmea_tui.widgets.floor_map import STYLE_SUSPECT, FloorMap, MapData
from kmea_tui.widgets.markers import MarkersTable, flags_of

RECORDING = Path(__file__).parent / "data" / "telemetry_sim.jsonl"
SCENE = "sim:misplaced?robots=true"


def _records() -> list[dict]:
    return [json.loads(line) for line in RECORDING.read_text().splitlines()]


def recorded_suspects() -> dict[int, set[int]]:
    """Recorded frame number (= simulator frame index) -> ids the daemon flagged suspect."""
    return {r["body"]["frame"]: {m["id"] for m in r["body"]["markers"] if m["suspect"]}
            for r in _records()[1:] if r["topic"] == "markers"}


def _last(topic: str, path: Path) -> dict:
    bodies = [json.loads(line) for line in path.read_text().splitlines()[1:]]
    return [r["body"] for r in bodies if r["topic"] == topic][-1]


def test_suspect_ids_are_the_detectors() -> None:
    from kmea.sim import Renderer, scene_from_spec
    from kmea.vision.detection import DetectorConfig, MarkerDetector
    from kmea.vision.marker_pose import estimate_marker_poses

    scene = scene_from_spec(SCENE)
    wm = scene.effective_map()
    renderer = Renderer(scene)
    detector = MarkerDetector(DetectorConfig(dictionary=wm.dictionary))
    lengths = {i: 0.06 for i in (40, 41, 42)}
    robots = {r["frame"]: r for r in (rec["body"] for rec in _records()[1:]
                                      if rec["topic"] == "robots")}
    suspects = recorded_suspects()
    assert suspects[32] == {25}  # the stream shows what the tests below rely on
    for index, expected in suspects.items():
        frame = renderer.render(index)
        # The recording's frame numbers are the simulator's frames: same robot poses.
        for r in robots[index]["robots"]:
            tx, ty, _ = frame.truth.robots[r["name"]]
            assert np.hypot(r["x"] - tx, r["y"] - ty) < 0.005, (index, r["name"])
        det = detector.detect(frame.image)
        obs, diag = estimate_marker_poses(det.ids, det.corners, scene.camera, lengths, wm)
        assert {o.id for o in obs if o.suspect} == expected, index
        assert diag.n_suspect == len(expected)


def test_flag_letter() -> None:
    assert flags_of({"suspect": True}) == "S"
    assert flags_of({"ambiguous": True, "flipped": True, "suspect": True}) == "AFS"
    assert flags_of({"suspect": False, "rejected": True, "moved": True}) == "!R"


def test_map_draws_suspect_label_without_error_vector() -> None:
    from kmea_tui.canvas import BrailleCanvas

    def marker(mid: int, x: float, **kw) -> dict:
        return {"id": mid, "in_map": True, "detected": True, "x": x + 0.03, "y": 0.0,
                "map_x": x, "map_y": 0.0, "map_z": 0.0, **kw}

    fm = FloorMap()
    fm.set_data(MapData(markers=[marker(1, -0.5, suspect=False), marker(2, 0.5, suspect=True)]))

    def styles_on_canvas() -> dict:
        c = BrailleCanvas(60, 20)
        fm.draw(c)
        return {text: st for row in c.runs() for text, st in row if text.strip()}

    runs = styles_on_canvas()
    assert runs.get("2") == STYLE_SUSPECT and runs.get("1") != STYLE_SUSPECT
    vectors_with = sum(1 for st in runs.values() if st == "yellow")
    # The same marker not suspect gets its (magnified) error vector drawn.
    fm.set_data(MapData(markers=[marker(1, -0.5), marker(2, 0.5)]))
    assert sum(1 for st in styles_on_canvas().values() if st == "yellow") > vectors_with


async def _replayed(app: KmeaTui, pilot) -> None:
    end = time.monotonic() + DEADLINE  # a loaded machine replays slowly: wait, do not count
    while time.monotonic() < end and not (app.replay_done and app.config_loaded):
        await pilot.pause(0.01)
    assert app.replay_done and app.config_loaded


async def test_suspect_marker_flagged_in_table_summary_map_and_help() -> None:
    stream = RECORDING
    app = KmeaTui(RecordingClient(stream), theme="ansi-dark")
    async with app.run_test(size=(80, 24)) as pilot:
        await _replayed(app, pilot)
        table = app.query_one(MarkersTable)
        flags = {k: str(table.get_cell(k, "flags")) for k in table.rows}
        assert "S" in flags["25"]
        assert [k for k, f in flags.items() if "S" in f] == ["25"]
        assert str(table.get_cell("25", "error")) == "-"  # no LOO error for a suspect marker
        summary = str(app.query_one("#markers-summary").render())
        # 25 is not "moved"; 7 (moved 2 cm) is, by the daemon's decision and evidence.
        assert "suspect 1" in summary and "moved 1 (7 20>10 mm)" in summary
        assert "!" in flags["7"] and "!" not in flags["25"]

        # Map tab: 25's label has the suspect style (the braille canvas cached as strips).
        await pilot.press("4")
        await pilot.pause(0.1)
        fm = app.query_one(FloorMap)
        segs = [s for y in range(fm.size.height) for s in fm.render_line(y)._segments]
        label = [s for s in segs if s.text == "25"]
        assert label and label[0].style.bgcolor == Style.parse(STYLE_SUSPECT).bgcolor
        assert not [s for s in segs if s.text == "7" and s.style.bgcolor is not None]

        # Back on the table, '?' opens the help panel that explains the flags.
        await pilot.press("1")
        await pilot.press("question_mark")
        await pilot.pause(0.1)
        from textual.widgets import HelpPanel, Markdown

        panel = app.screen.query_one(HelpPanel)
        assert "suspect" in panel.query_one(Markdown).source
        await pilot.press("question_mark")
        await pilot.pause(0.05)
        assert not app.screen.query(HelpPanel)

        # A next frame where 25 is fine again: the row is updated in place, flag gone.
        row_before, added = table.rows["25"], table.rows_added
        body = _last("markers", stream)
        body["frame"] = 33
        for m in body["markers"]:
            m["suspect"] = False
        app.post_message(TelemetryBatch({"markers": body}))
        end = time.monotonic() + DEADLINE
        while time.monotonic() < end and "S" in str(table.get_cell("25", "flags")):
            await pilot.pause(0.01)
        assert "S" not in str(table.get_cell("25", "flags"))
        assert table.rows["25"] is row_before and table.rows_added == added
        assert "suspect 0" in str(app.query_one("#markers-summary").render())


@pytest.mark.parametrize(("tab", "key", "theme"), [
    ("markers", "1", "textual-dark"), ("map", "4", "textual-dark"), ("map", "4", "ansi-dark")])
def test_suspect_snapshot(snap_compare, tab: str, key: str, theme: str) -> None:
    assert snap_compare(KmeaTui(RecordingClient(RECORDING), theme=theme), press=[key],
                        terminal_size=(80, 24),
                        run_before=lambda pilot: _replayed(pilot.app, pilot))
