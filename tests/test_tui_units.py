"""kmea-tui building blocks: braille canvas, viewport, magnification, form parsing, status line."""

from __future__ import annotations

import json
import math

import pytest

from kmea.wire.protocol import PROTOCOL_VERSION
from kmea_tui.app import connection_state, terminal_has_16_colours
from kmea_tui.canvas import BrailleCanvas, Viewport, heading_arrow, nice_magnification
from kmea_tui.cli import main as tui_main
from kmea_tui.client import RecordingClient
from kmea_tui.screens.robot_edit import parse_robot
from kmea_tui.widgets.config_form import parse_value, show_value
from kmea_tui.widgets.floor_map import marker_error_vector
from kmea_tui.widgets.log_panel import human_bytes
from kmea_tui.widgets.markers import flags_of, moved_ids, moved_note
from kmea_tui.widgets.status_bar import status_text


def test_braille_dots_map_to_unicode_bits() -> None:
    c = BrailleCanvas(2, 1)
    c.dot(0, 0)  # top-left dot of cell 0: bit 0x01
    c.dot(3, 3)  # bottom-right dot of cell 1: bit 0x80
    assert c.render().plain == chr(0x2801) + chr(0x2880)
    assert c.is_set(0, 0) and c.is_set(3, 3) and not c.is_set(1, 0)
    c.dot(-1, 0)
    c.dot(4, 0)  # outside: ignored, no exception
    assert c.render().plain == chr(0x2801) + chr(0x2880)


def test_text_replaces_dots_and_is_clipped() -> None:
    c = BrailleCanvas(3, 2)
    c.line(0, 0, 5, 0)
    c.text(2, 0, "42")  # the second character falls outside
    rows = c.render().plain.split("\n")
    assert rows[0][2] == "4" and len(rows[0]) == 3
    assert rows[1] == "   "
    assert not c.free(2, 0, 1) and c.free(0, 1, 3) and not c.free(2, 1, 2)


def test_viewport_is_to_scale_and_flips_y() -> None:
    vp = Viewport(-0.85, 0.85, -0.6, 0.6, 160, 80)
    x0, y0 = vp.to_dots(-0.85, 0.6)
    x1, y1 = vp.to_dots(0.85, -0.6)
    # Same dots per metre on both axes: the floor's aspect ratio is kept.
    assert (x1 - x0) / (y1 - y0) == pytest.approx(1.7 / 1.2)
    assert y0 < y1  # world +y is up on screen
    assert x0 >= -1e-9 and x1 <= 159 + 1e-9 and y0 >= -1e-9 and y1 <= 79 + 1e-9
    # Height-limited here: the rectangle fills the height.
    assert y1 - y0 == pytest.approx(79)


@pytest.mark.parametrize(("err", "target", "expected"), [
    (0.001, 0.136, 100.0), (0.002, 0.136, 50.0), (0.0001, 0.136, 1000.0),
    (0.036, 0.136, 2.0), (0.5, 0.136, 1.0), (0.0, 0.136, 100.0), (1e-9, 0.1, 10000.0),
])
def test_nice_magnification(err: float, target: float, expected: float) -> None:
    m = nice_magnification(err, target)
    assert m == expected
    if err > 0 and 1 < m < 10000:
        assert m * err <= target + 1e-12  # never longer than the target


def test_heading_arrow() -> None:
    assert [heading_arrow(k * math.pi / 4) for k in range(8)] == list("→↗↑↖←↙↓↘")
    assert heading_arrow(-math.pi / 2) == "↓"


def test_moved_is_the_daemons_flag_with_its_evidence() -> None:
    # The UI has no rule of its own: a large error without the daemon's "moved" is not moved.
    markers = [{"id": i, "in_map": True, "error": 0.002, "moved": False} for i in range(10)]
    markers.append({"id": 99, "in_map": True, "error": 0.05, "moved": False})
    markers.append({"id": 7, "in_map": True, "error": 0.004, "moved": True,
                    "moved_offset": 0.0213, "moved_threshold": 0.01, "moved_frames": 5})
    assert moved_ids(markers) == {7}
    assert moved_note(markers[-1]) == "7 21>10 mm"
    assert flags_of({"ambiguous": True, "rejected": True, "moved": True}) == "!AR"
    assert flags_of(markers[10]) == ""


def test_error_vector_needs_estimate_and_map() -> None:
    assert marker_error_vector({"detected": True, "x": 1.0, "y": 2.0,
                                "map_x": 0.9, "map_y": 2.05}) == pytest.approx((0.1, -0.05))
    assert marker_error_vector({"detected": False, "x": None, "y": None,
                                "map_x": 0.9, "map_y": 2.0}) is None
    assert marker_error_vector({"detected": True, "x": 1.0, "y": 2.0,
                                "map_x": None, "map_y": None}) is None


def test_parse_robot() -> None:
    r = parse_robot("amr3", "40, 41", "0.25", "", "udp:127.0.0.1:9001, udp:10.0.0.2:9000")
    assert r == {"name": "amr3", "markers": [40, 41], "height": 0.25, "length": 0.06,
                 "separation": 0.10,
                 "destinations": ["udp:127.0.0.1:9001", "udp:10.0.0.2:9000"]}
    assert parse_robot("a", "1,2", "", "", "", "0.2")["separation"] == 0.2
    with pytest.raises(ValueError, match="separation"):
        parse_robot("a", "1,2", "", "", "", "0")
    assert parse_robot("a", "42", "", "0.05", "")["markers"] == [42]
    for bad, field in ((("", "42", "", "", ""), "name"), (("a", "1,2,3", "", "", ""), "markers"),
                       (("a", "x", "", "", ""), "markers"), (("a", "4,4", "", "", ""), "markers"),
                       (("a", "4", "high", "", ""), "height"),
                       (("a", "4", "", "0", ""), "length")):
        with pytest.raises(ValueError, match=field):
            parse_robot(*bad)


def test_parse_and_show_values_round_trip() -> None:
    for v in (1.0, 3, True, "DICT_6X6_250", [1, 2], {"adaptiveThreshWinSizeMax": 31}, {}):
        assert parse_value(show_value(v)) == v
    assert parse_value("subpix") == "subpix"  # a bare word is a string


def test_status_text_fits_and_orders() -> None:
    frame = {"fps": 29.94, "dropped": 3,
             "timings_ms": {"capture": 1.0, "detect": 12.0, "pose": 0.5, "estimate": 0.2,
                            "loo": 0.4, "filter": 0.0, "robots": 0.1, "output": 0.3,
                            "total": 14.5}}
    narrow = status_text("connected", frame, width=60).plain
    wide = status_text("connected", frame, width=200).plain
    assert narrow.startswith("● connected  29.9 fps  dropped 3  14.5 ms: det 12.0")
    assert len(narrow) <= 60 and "cap 1.0" in wide and "cap" not in narrow
    bad = status_text("connected", {**frame, "ok": False, "reason": "2 references"}, 200).plain
    assert "not estimated: 2 references" in bad
    assert "disconnected (no reply" in status_text("disconnected", None, 80,
                                                   "no reply from x").plain


def test_colours() -> None:
    assert terminal_has_16_colours({"TERM": "xterm"})
    assert terminal_has_16_colours({"TERM": "linux"})
    assert not terminal_has_16_colours({"TERM": "xterm-256color"})
    assert not terminal_has_16_colours({"TERM": "xterm", "COLORTERM": "truecolor"})
    assert human_bytes(123) == "123 B" and human_bytes(123456) == "123.5 kB"


async def test_recording_client_names_bad_lines(tmp_path) -> None:
    good = {"topic": "event", "body": {"v": PROTOCOL_VERSION, "t": 1.0, "level": "info",
                                       "text": "hello"}, "dt": 0.0}
    p = tmp_path / "rec.jsonl"
    p.write_text(json.dumps(good) + "\n" + "{not json\n")
    with pytest.raises(ValueError, match=r"rec.jsonl:2: not JSON"):
        RecordingClient(p)
    p.write_text(json.dumps({"topic": "frame", "body": {"v": 1}}) + "\n")
    with pytest.raises(ValueError, match=r"rec.jsonl:1: field 'v'"):
        RecordingClient(p)
    # The typed decoder: a body of the right version with a field of the wrong type.
    p.write_text(json.dumps({"topic": "event", "body": {**good["body"], "t": "now"}}) + "\n")
    with pytest.raises(ValueError, match=r"rec.jsonl:1: event: field 't': expected float"):
        RecordingClient(p)
    cfg = {"ok": True, "cmd": "get_config", "config": {"a": 1}, "config_file": None,
           "config_files": [], "overlay_file": "x.local.toml", "live_keys": []}
    p.write_text(json.dumps({"header": {"get_config": cfg}}) + "\n" + json.dumps(good) + "\n")
    rc = RecordingClient(p)
    assert len(rc.messages) == 1
    await rc.open()
    assert await rc.request("get_config") == cfg
    assert (await rc.request("ping"))["ok"] is True
    reply = await rc.request("log_start", path="x.csv")
    assert reply["ok"] is False and "no daemon" in reply["error"]
    assert await rc.recv(0.01) == [("event", good["body"])]
    assert rc.ended and await rc.recv(0.01) == []


def test_connection_state() -> None:
    assert connection_state(None, "", None, 10.0, 2.0)[0] == "connecting"
    assert connection_state(False, "no reply from x", 9.9, 10.0, 2.0) == (
        "disconnected", "no reply from x")
    assert connection_state(True, "", None, 10.0, 2.0) == ("stale", "no telemetry yet")
    assert connection_state(True, "", 9.0, 10.0, 2.0) == ("connected", "")
    assert connection_state(True, "", 7.5, 10.0, 2.0) == ("stale", "no telemetry for 2 s")


def test_cli_refuses_bad_arguments_with_one_line(tmp_path, capsys) -> None:
    cases = [
        (["--telemetry", "localhost:5555"], "--telemetry 'localhost:5555'"),
        (["--replay", str(tmp_path / "missing.jsonl")], "cannot read recording"),
        (["--screenshots", str(tmp_path)], "--screenshots needs --replay"),
        (["--replay", str(tmp_path / "r.jsonl"), "--screenshots", str(tmp_path),
          "--size", "80"], "--size '80'"),
        (["--rate", "100"], "--rate"),
    ]
    (tmp_path / "r.jsonl").write_text("")
    for argv, message in cases:
        assert tui_main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1, (argv, err)


def test_an_output_stopped_by_the_disk_shows_in_the_status_bar_and_the_log_tab() -> None:
    from kmea_tui.widgets.log_panel import LogPane
    from kmea_tui.widgets.status_bar import output_alert

    ok = {"logging": {"active": True, "error": None}, "recording": {"active": False}}
    assert output_alert(ok) == "" and output_alert(None) == ""
    full = {"logging": {"active": False, "path": "/d/run.csv",
                        "error": "CSV log /d/run.csv: write failed: No space left on device"},
            "recording": {"active": False, "error": "recording /d/r.jsonl: stopped after 3 "
                                                    "frames: 9.0 MB free"}}
    alert = output_alert(full)
    assert alert == "log and recording stopped (Log tab)"
    line = status_text("connected", {"fps": 30.0, "dropped": 0}, 80, alert=alert).plain
    assert line.startswith("● connected  log and recording stopped (Log tab)  30.0 fps")
    shown = LogPane._state_line("CSV log", full["logging"], "rows", "rows").plain
    assert "stopped" in shown and "No space left on device" in shown


def test_a_fusion_nodes_camera_clocks_show_and_one_far_off_is_an_alert() -> None:
    from kmea_tui.widgets.robots import cameras_text
    from kmea_tui.widgets.status_bar import output_alert

    inputs = [{"label": "cam0", "state": "used", "clock_offset_s": 0.002},
              {"label": "cam1", "state": "refused", "clock_offset_s": 3600.0},
              {"label": "cam2", "state": "waiting", "clock_offset_s": None}]
    assert output_alert({"inputs": inputs}) == "cam1 clock +3600.0 s"
    assert output_alert({"inputs": inputs[:1]}) == ""
    text = cameras_text(inputs)
    assert text.plain == (" · cam0 used clock +2 ms · cam1 refused clock +3600.0 s"
                          " · cam2 waiting clock -")
    assert any("red" in str(span.style) for span in text.spans)
