"""The "looks displaced" event: persistence (kmead.displacement) and the daemon end to end.

A robot passing over a floor marker's corner used to raise "marker 26 looks displaced by
65 mm" from one frame of ``make run``; a marker moved on the floor (here: moved in the map)
must still be reported.
"""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
from kmead.displacement import DisplacementMonitor

from kmea.maps import default_map
from kmead import cli

NET = ["--set", 'network.telemetry="tcp://127.0.0.1:*"',
       "--set", 'network.control="tcp://127.0.0.1:*"']
UNPACED = ["--set", "source.fps=0"]
SMALL = ["--set", "source.width=640", "--set", "source.height=480"]


def feed(monitor: DisplacementMonitor, series: list[float | None], mid: int = 7) -> list[int]:
    """Frames (indexes into series) where ``mid`` looks displaced; None = not measured."""
    fired = []
    for i, e in enumerate(series):
        if mid in monitor.update({} if e is None else {mid: e}):
            fired.append(i)
    return fired


def test_single_frame_glitch_is_not_an_event() -> None:
    m = DisplacementMonitor(0.02, 5)
    assert feed(m, [0.001, 0.065, 0.001, 0.002, 0.034, 0.001, 0.001, 0.001]) == []
    # Two bad frames in a row are still a minority of five.
    assert feed(DisplacementMonitor(0.02, 5), [0.001, 0.001, 0.001, 0.05, 0.05, 0.001]) == []


def test_persistent_displacement_is_an_event_after_three_frames() -> None:
    m = DisplacementMonitor(0.02, 5)
    assert feed(m, [0.05] * 6) == [2, 3, 4, 5]
    assert m.update({7: 0.05}) == {7: pytest.approx(0.05)}
    # Most of the window above the threshold, with good frames in between.
    assert feed(DisplacementMonitor(0.02, 5), [0.03, 0.001, 0.03, 0.001, 0.03]) == [2, 4]


def test_unmeasured_frames_keep_the_window() -> None:
    # A marker hidden (or suspect) in between: the frames where it was measured count.
    m = DisplacementMonitor(0.02, 5)
    assert feed(m, [0.04, None, None, 0.04, None, 0.04]) == [5]
    assert m.update({8: 0.5}) == {}  # windows are per marker


def test_window_of_one_frame_is_the_old_rule() -> None:
    assert feed(DisplacementMonitor(0.02, 1), [0.001, 0.03, 0.001]) == [1]
    with pytest.raises(ValueError, match="frames must be >= 1"):
        DisplacementMonitor(0.02, 0)


def test_make_run_frames_with_a_robot_over_markers_raise_no_event(
        tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    # Default scene at 1640x1232, frames 0-7: robot plates over corners of floor markers 26
    # (frames 2-5) and 0 (frames 6-7) gave 10-65 mm single-frame LOO errors and four events.
    out = tmp_path / "run.csv"
    assert cli.main(["--source", "sim", "--headless", "--frames", "8", "--log", str(out),
                     *UNPACED, *NET]) == 0
    assert "looks displaced" not in capsys.readouterr().err
    with open(out, newline="") as f:
        rows = [r for r in csv.DictReader(f) if r["kind"] == "marker"]
    errors = [float(r["error"]) for r in rows if r["error"]]
    assert len(errors) > 8 * 30 and max(errors) < 0.01
    # Marker 26 is still estimated and logged in the frames where it is partly hidden
    # (suspect), without an error (in no statistics then); once the robot has passed it is a
    # reference again, with a small error.
    m26 = {int(r["frame"]): r["error"] for r in rows if r["id"] == "26"}
    assert set(m26) == {2, 3, 4, 5, 6, 7}
    assert not any(m26[i] for i in (2, 3))
    assert m26[6] and m26[7] and max(float(m26[6]), float(m26[7])) < 0.002


def moved_map(tmp_path: Path) -> Path:
    m = default_map()
    path = tmp_path / "moved.csv"
    path.write_text("id,x,y,z\n" + "".join(
        f"{mid},{float(mk.position[0]) + (0.05 if mid == 16 else 0.0)!r},"
        f"{float(mk.position[1])!r},0\n" for mid, mk in m.markers.items() if mk.on_floor))
    return path


@pytest.mark.parametrize(("frames", "window", "reported"),
                         [(2, 5, False), (4, 5, True), (1, 1, True)])
def test_marker_moved_5_cm_is_reported_once_persistent(
        tmp_path: Path, capsys: pytest.CaptureFixture, frames: int, window: int,
        reported: bool) -> None:
    # The map says marker 16 is 5 cm right of where it is; plain KMEA (no robust rejection).
    assert cli.main(["--source", "sim", "--map", str(moved_map(tmp_path)), "--headless",
                     "--frames", str(frames), "--set", f"stats.displaced_frames={window}",
                     *SMALL, *UNPACED, *NET]) == 0
    err = capsys.readouterr().err
    assert ("marker 16 looks displaced by" in err) == reported
