"""kmea-tui keeps up with a fast telemetry stream on a real PUB socket.

A publisher sends the recorded frame/markers/robots/stats messages at 100 frames/s (faster
than any camera here) for 1.5 s, every frame with a new frame number and moved estimates.
The UI must coalesce (drop stale messages), end up showing the last frame, and update the
tables in place: same rows, no clear(), cells updated. No wall-clock assertions.
"""

from __future__ import annotations

import asyncio
import copy
import json
import time
from pathlib import Path

import zmq
import zmq.asyncio
from deadlines import DEADLINE

from kmea.wire import protocol
from kmea_tui.app import KmeaTui
from kmea_tui.client import DaemonClient
from kmea_tui.widgets.markers import MarkersTable
from kmea_tui.widgets.robots import RobotsTable

RECORDING = Path(__file__).parent / "data" / "telemetry_sim.jsonl"
RATE_HZ = 100
SECONDS = 1.5


def _templates() -> dict[str, dict]:
    out: dict[str, dict] = {}
    for line in RECORDING.read_text().splitlines():
        rec = json.loads(line)
        if rec.get("topic") in ("frame", "markers", "robots", "stats"):
            out[rec["topic"]] = rec["body"]
    return out


def _bodies(templates: dict[str, dict], frame: int) -> list[tuple[str, dict]]:
    out = []
    for topic, tmpl in templates.items():
        body = copy.deepcopy(tmpl)
        body["frame"] = frame
        if topic == "markers":
            for m in body["markers"]:
                if m.get("x") is not None:
                    m["x"] = round(m["x"] + 1e-4 * frame, 6)  # every frame moves everything
        if topic == "robots":
            for r in body["robots"]:
                r["sent"] = frame
        out.append((topic, body))
    return out


async def test_fast_stream_is_coalesced_and_tables_update_in_place() -> None:
    templates = _templates()
    ctx = zmq.asyncio.Context()
    pub = ctx.socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    port = pub.bind_to_random_port("tcp://127.0.0.1")
    # No control socket behind the address: the UI must show the stream all the same.
    client = DaemonClient(f"tcp://127.0.0.1:{port}", "tcp://127.0.0.1:1", timeout=0.2)
    app = KmeaTui(client, theme="textual-dark", ping_period=0.5)
    n_frames = int(RATE_HZ * SECONDS)
    try:
        async with app.run_test(size=(80, 24)) as pilot:
            markers = app.query_one(MarkersTable)
            robots = app.query_one(RobotsTable)
            clears: list[str] = []
            for table in (markers, robots):
                orig = table.clear

                def counting_clear(*a, _t=table, _orig=orig, **k):  # type: ignore[no-untyped-def]
                    clears.append(_t.id or "?")
                    return _orig(*a, **k)

                table.clear = counting_clear  # type: ignore[method-assign]

            # Wait until the subscription is through before the measured burst.
            for _ in range(300):
                for topic, body in _bodies(templates, 0):
                    await pub.send_multipart(protocol.encode(topic, body))
                await pilot.pause(0.02)
                if markers.row_count:
                    break
            assert markers.row_count, "telemetry never reached the UI"
            rows_before = {k: markers.rows[k] for k in markers.rows}
            added_before = markers.rows_added
            received_before = app.received

            for frame in range(1, n_frames + 1):
                for topic, body in _bodies(templates, frame):
                    await pub.send_multipart(protocol.encode(topic, body))
                await asyncio.sleep(1 / RATE_HZ)

            # The last frame shows up once the burst is over.
            last = n_frames
            end = time.monotonic() + DEADLINE
            while time.monotonic() < end and not (
                    (app.frame or {}).get("frame") == last
                    and (app.markers_body or {}).get("frame") == last):
                await pilot.pause(0.01)
            assert app.frame is not None and app.frame["frame"] == last
            summary = str(app.query_one("#markers-summary").render())
            assert f"frame {last}" in summary

            sent = n_frames * len(templates)
            got = app.received - received_before
            print(f"sent {sent}, received {got}, coalesced {app.coalesced}, "
                  f"UI batches {app.batches}")
            # Far fewer UI updates than messages: stale messages were dropped, not queued.
            assert app.coalesced > 0
            assert app.batches < got / 4 < sent
            # Rows updated in place: same keys, same Row objects, nothing re-added, no clear().
            assert set(markers.rows) == set(rows_before)
            assert all(markers.rows[k] is rows_before[k] for k in rows_before)
            assert markers.rows_added == added_before and markers.rows_removed == 0
            assert markers.cells_updated > 0
            # The Robots tab is hidden: its table is not repainted at all ...
            assert robots.rows_added == 0 and robots.cells_updated == 0
            assert clears == []
            # ... and the cells show the newest values.
            newest = dict(_bodies(templates, last))["markers"]["markers"]
            for mk in newest:
                if mk.get("x") is not None:
                    assert str(markers.get_cell(str(mk["id"]), "x")) == f"{mk['x']:.3f}"
            # ... until it is shown: then it holds the newest robots at once.
            await pilot.press("2")
            await pilot.pause(0.05)
            newest_robots = dict(_bodies(templates, last))["robots"]["robots"]
            assert set(robots.rows) == {r["name"] for r in newest_robots}
            for r in newest_robots:
                assert str(robots.raw[r["name"]]["sent"]) == str(last)
    finally:
        pub.close(linger=0)
        ctx.term()
