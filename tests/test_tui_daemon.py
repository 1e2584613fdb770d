"""kmea-tui driven by Pilot against a REAL kmead on the simulated floor over loopback.

The daemon runs as a subprocess (``python -m kmead.cli --source sim --headless``, 640x480
frames to keep it light) on free ports. Waits have generous timeouts; nothing asserts speed.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from deadlines import DEADLINE, JOIN
from textual.widgets import Select

from kmea_tui.app import KmeaTui
from kmea_tui.client import DaemonClient
from kmea_tui.widgets.log_panel import LogPane
from kmea_tui.widgets.markers import MarkersTable
from kmea_tui.widgets.robots import RobotsTable

CSV_HEADER = "frame,timestamp,algorithm,kind,id,x,y,z,yaw,error,refs"
START_TIMEOUT = 60.0
WAIT = DEADLINE


class Daemon:
    """One kmead subprocess; ``telemetry``/``control`` are its bound endpoints."""

    def __init__(self, cwd: Path, telemetry: str = "tcp://127.0.0.1:*",
                 control: str = "tcp://127.0.0.1:*", source: str = "sim",
                 extra: tuple[str, ...] = ("--algorithm", "kmea")) -> None:
        self.cwd = cwd
        self.stderr_path = cwd / f"kmead-{time.monotonic_ns()}.err"
        # Its own config home: a plain start reads (and Save writes) the per-user overlay.
        self.env = {**os.environ, "XDG_CONFIG_HOME": str(cwd / "config-home")}
        # The paper's KMEA by default (not the default corner-pnp): the algorithm test walks
        # the list from it. ``extra``: more command-line arguments.
        cmd = [sys.executable, "-m", "kmead.cli", "--source", source, "--headless", *extra,
               "--set", f'network.telemetry="{telemetry}"',
               "--set", f'network.control="{control}"',
               "--set", "source.width=640", "--set", "source.height=480",
               "--set", "network.status_period_s=0.5",
               # 5 frames/s: Pilot waits for the app to idle after each key press.
               "--set", "source.fps=5"]
        with open(self.stderr_path, "w") as err:
            self.proc = subprocess.Popen(cmd, cwd=cwd, stdout=subprocess.DEVNULL, stderr=err,
                                         env=self.env)
        deadline = time.monotonic() + START_TIMEOUT
        while time.monotonic() < deadline:
            text = self.stderr_path.read_text()
            m = re.search(r"telemetry (tcp://\S+), control (tcp://\S+)", text)
            if m:
                self.telemetry, self.control = m.group(1), m.group(2)
                return
            if self.proc.poll() is not None:
                raise RuntimeError(f"kmead exited with {self.proc.returncode}:\n{text}")
            time.sleep(0.05)
        self.stop()
        raise RuntimeError(f"kmead did not report its endpoints:\n{self.stderr_path.read_text()}")

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=JOIN)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


@pytest.fixture(scope="module")
def daemon(tmp_path_factory) -> Iterator[Daemon]:
    d = Daemon(tmp_path_factory.mktemp("kmead"))
    yield d
    d.stop()


async def wait_for(pilot, cond: Callable[[], bool], what: str, timeout: float = WAIT) -> None:
    t0 = time.monotonic()
    deadline = t0 + timeout
    while time.monotonic() < deadline:
        if cond():
            print(f"{time.monotonic() - t0:5.2f} s: {what}")
            return
        await pilot.pause(0.05)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def _app(d: Daemon) -> KmeaTui:
    return KmeaTui(DaemonClient(d.telemetry, d.control, timeout=1.0), theme="textual-dark",
                   ping_period=0.5)


async def test_marker_and_robot_tables_fill(daemon: Daemon) -> None:
    app = _app(daemon)
    async with app.run_test(size=(80, 24)) as pilot:
        markers = app.query_one(MarkersTable)
        await wait_for(pilot, lambda: markers.row_count >= 49 and app.markers_body is not None,
                       "the 49 map markers in the table")
        await wait_for(pilot, lambda: app.connection_state == "connected", "connected state")
        raw = markers.raw
        # Every map marker of the RobotAtFactory floor is listed, most are detected, and
        # the robots' markers appear as detected markers outside the map.
        assert {str(i) for i in (13, 16, 4)} <= set(raw)
        assert sum(1 for m in raw.values() if m.get("in_map") and m.get("detected")) >= 10
        assert any(not m.get("in_map") and m.get("detected") for m in raw.values())
        assert str(markers.get_cell("13", "map_x")) == "0.000"
        # Sort by LOO error, largest first, with the keyboard (s cycles, S reverses).
        await pilot.press(*["s"] * 8, "S")
        assert markers.sort_column == "error" and markers.sort_reverse
        order = [markers.raw[str(markers.get_row_at(i)[0])] for i in range(markers.row_count)]
        errs = [m["error"] for m in order if isinstance(m.get("error"), (int, float))]
        assert errs and errs == sorted(errs, reverse=True)
        assert all(isinstance(m.get("error"), (int, float)) for m in order[:len(errs)])
        robots = app.query_one(RobotsTable)
        await pilot.press("2")  # hidden tabs are not repainted; shown, they fill at once
        await wait_for(pilot, lambda: {"amr1", "amr2"} <= set(robots.rows),
                       "robots amr1 and amr2")
        status = str(app.query_one("#status").render())
        assert "connected" in status and "fps" in status
        # Statistics tab: x resets the daemon's statistics (the reply is noted in the Log).
        await pilot.press("3", "x", "6")
        log = app.query_one("#events")
        await wait_for(pilot, lambda: any("reset_stats" in str(line.text)
                                          for line in log.lines), "reset_stats reply")
        assert any("✓ reset_stats" in str(line.text) for line in log.lines)


async def test_algorithm_change_from_config_tab(daemon: Daemon) -> None:
    app = _app(daemon)
    async with app.run_test(size=(80, 24)) as pilot:
        await wait_for(pilot, lambda: app.config_loaded and app.frame is not None,
                       "configuration and telemetry")
        await wait_for(pilot, lambda: app.frame["algorithm"] == "kmea", "algorithm kmea")
        await pilot.press("5")
        select = app.query_one("#algorithm", Select)
        assert select.has_focus and select.value == "kmea"
        # The list is the daemon's (status.algorithms), not a registry of the UI's own.
        await wait_for(pilot, lambda: app.status is not None, "status")
        options = [v for _, v in select._options if isinstance(v, str)]
        assert options == app.status["algorithms"] and len(options) > 3
        # Keyboard only: open the list, go to the entry below kmea (lmea), choose it.
        assert options[options.index("kmea") + 1] == "lmea"
        await pilot.press("enter")
        await pilot.pause(0.2)
        await pilot.press("down", "enter")
        await wait_for(pilot, lambda: select.value == "lmea", "the select to show lmea")
        # The daemon's own telemetry reports the new algorithm ...
        await wait_for(pilot, lambda: app.frame["algorithm"] == "lmea",
                       "telemetry frames with algorithm lmea")
        # ... and so does its configuration, re-read after the change.
        await wait_for(pilot, lambda: app.query_one("#config-pane").config
                       .get("estimator", {}).get("algorithm") == "lmea", "get_config lmea")
        check = DaemonClient(daemon.telemetry, daemon.control)
        await check.open()
        try:
            reply = await check.request("get_config")
            assert reply["ok"] and reply["config"]["estimator"]["algorithm"] == "lmea"
            # Leave the shared daemon as we found it.
            assert (await check.request("set", key="estimator.algorithm", value="kmea"))["ok"]
        finally:
            check.close()


async def test_log_started_from_log_tab_creates_the_file(daemon: Daemon) -> None:
    app = _app(daemon)
    csv = daemon.cwd / "tui-log.csv"
    async with app.run_test(size=(80, 24)) as pilot:
        await wait_for(pilot, lambda: app.connection_state == "connected", "connected")
        await pilot.press("6")
        app.query_one("#log-path").focus()
        await pilot.press(*"tui-log.csv")
        await pilot.press("tab")  # to the "CSV log" button
        assert app.focused is not None and app.focused.id == "log-toggle"
        await pilot.press("enter")
        await wait_for(pilot, lambda: csv.exists() and len(csv.read_text().splitlines()) > 5,
                       f"{csv} with rows")
        assert csv.read_text().splitlines()[0] == CSV_HEADER
        pane = app.query_one(LogPane)
        await wait_for(pilot, lambda: pane.logging.get("active") is True
                       and str(pane.logging.get("path", "")).endswith("tui-log.csv"),
                       "the Log tab to show the running log")
        state = str(app.query_one("#log-state").render())
        assert "● on" in state and "tui-log.csv" in state and "rows" in state
        await pilot.press("l")  # the Log tab's key toggles it off
        await wait_for(pilot, lambda: pane.logging.get("active") is False, "log stopped")
        rows = len(csv.read_text().splitlines())
        assert rows > 5


async def test_stopping_daemon_shows_disconnected_and_restart_reconnects(tmp_path) -> None:
    first = Daemon(tmp_path)
    tel, ctl = first.telemetry, first.control
    second: Daemon | None = None
    app = _app(first)
    try:
        async with app.run_test(size=(80, 24)) as pilot:
            await wait_for(pilot, lambda: app.connection_state == "connected", "connected")
            first.stop()
            # The daemon announced its end on telemetry: "daemon stopped", not frozen data.
            await wait_for(pilot, lambda: app.connection_state == "stopped",
                           "stopped after the daemon announced it")
            status = str(app.query_one("#status").render())
            assert "daemon stopped" in status and "fps" not in status
            frames_before = app.received
            second = Daemon(tmp_path, telemetry=tel, control=ctl)  # same endpoints
            await wait_for(pilot, lambda: app.connection_state == "connected",
                           "reconnected to the restarted daemon")
            await wait_for(pilot, lambda: app.received > frames_before,
                           "telemetry from the restarted daemon")
            assert "connected" in str(app.query_one("#status").render())
    finally:
        first.stop()
        if second is not None:
            second.stop()


async def test_config_edits_apply_live_and_save_writes_the_overlay(daemon: Daemon) -> None:
    app = _app(daemon)
    async with app.run_test(size=(80, 24)) as pilot:
        await wait_for(pilot, lambda: app.config_loaded, "configuration")
        pane = app.query_one("#config-pane")
        await pilot.press("5")
        # The form offers a technician's detector keys, not the advanced ones.
        await wait_for(pilot, lambda: bool(list(app.query(".detector-option"))), "the detector")
        names = {i.name for i in app.query(".detector-option")}
        assert "dictionary" in names and "marker_length" in names
        assert not names & {"workers", "parameters", "fixed_camera"}
        # Filter alpha: type a value, Enter applies it live.
        alpha = app.query_one("#filter-alpha")
        alpha.focus()
        alpha.value = ""
        await pilot.press(*"0.5", "enter")
        await wait_for(pilot, lambda: pane.config.get("filter", {}).get("alpha") == 0.5,
                       "filter.alpha = 0.5 in the daemon's configuration")
        # Robots: add one with the form (a, fill in, Enter), then remove it again (d).
        table = app.query_one("#robots-config")
        table.focus()
        n = table.row_count
        await pilot.press("a")
        await pilot.pause(0.2)
        await pilot.press(*"amr3", "tab", *"43")
        # (Typing through Pilot is slow while telemetry streams; the rest is set directly.)
        app.screen.query_one("#robot-destinations").value = "udp:127.0.0.1:9003"
        app.screen.query_one("#robot-height").value = "0.25"
        await pilot.press("enter")
        await wait_for(pilot, lambda: [r.get("name") for r in pane.robots][-1:] == ["amr3"],
                       "robot amr3 in the daemon's configuration")
        amr3 = pane.robots[-1]
        assert amr3["markers"] == [43] and amr3["destinations"] == ["udp:127.0.0.1:9003"]
        assert amr3["height"] == 0.25
        await wait_for(pilot, lambda: table.row_count == n + 1, "the robots table to grow")
        # The live robots table follows the daemon (amr3 is configured, not seen).
        await wait_for(pilot, lambda: "amr3" in {r.get("name") for r in
                                                 (app.robots_body or {}).get("robots", [])},
                       "amr3 in the robots telemetry")
        table.focus()
        table.move_cursor(row=n)
        await pilot.press("d")
        await wait_for(pilot, lambda: "amr3" not in {r.get("name") for r in pane.robots},
                       "amr3 removed")
        # Save: the daemon writes its overlay file, never the commented configuration.
        await pilot.press("ctrl+s")
        # Started without --config: Save writes the per-user overlay, which the next plain
        # start reads (kmead --check shows the effective configuration without starting).
        overlay = daemon.cwd / "config-home" / "kmead" / "kmead.local.toml"
        # The changes are on trial for 20 frames (kmead.run.rollback): saved once it passed.
        await wait_for(pilot, lambda: overlay.exists() and "alpha = 0.5" in overlay.read_text(),
                       f"alpha = 0.5 in {overlay}")
        check = subprocess.run([sys.executable, "-m", "kmead.cli", "--check"], cwd=daemon.cwd,
                               env=daemon.env, capture_output=True, text=True, timeout=60)
        assert check.returncode == 0, check.stderr
        assert "alpha = 0.5" in check.stdout and str(overlay) in check.stdout
        assert str(overlay) in str(app.query_one("#save-note").render()).replace("\n", "")
