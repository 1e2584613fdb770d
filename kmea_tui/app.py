"""The kmea-tui application: a terminal UI on a running kmead (or a recording of one).

Data flow: ONE exclusive async worker (:meth:`KmeaTui.stream`) reads the telemetry socket,
keeps only the newest message per topic and posts a :class:`TelemetryBatch` at most every
``ui_period`` seconds, and only after the UI has applied the previous one (so a fast daemon
can never queue work in the UI: older messages are dropped and counted as coalesced).
Tables are keyed by marker id / robot name and updated in place.
A second small worker pings the control socket every second for the connection state.
"""

from __future__ import annotations

import asyncio
import math
import os
import time
from collections import deque
from contextlib import suppress
from pathlib import Path
from typing import Any

from textual import work
from textual.app import App, ComposeResult, ScreenStackError
from textual.binding import Binding
from textual.css.query import NoMatches
from textual.widgets import Footer, HelpPanel, Input, Select, Static, TabbedContent, TabPane

from kmea.wire import protocol
from kmea_tui.client import DaemonClient, RecordingClient
from kmea_tui.messages import ConnectionChanged, ControlReply, ControlRequest, TelemetryBatch
from kmea_tui.screens.quit_confirm import QuitScreen
from kmea_tui.widgets.camera_view import CameraFrame, CameraPane, FrameError, display_size
from kmea_tui.widgets.config_form import ConfigPane
from kmea_tui.widgets.floor_map import FloorMap, MapData, MapPane
from kmea_tui.widgets.live_table import LiveTable
from kmea_tui.widgets.log_panel import LogPane
from kmea_tui.widgets.markers import MarkersPane, moved_ids
from kmea_tui.widgets.robots import RobotsPane
from kmea_tui.widgets.stats import StatsPane
from kmea_tui.widgets.status_bar import StatusBar, output_alert

Client = DaemonClient | RecordingClient

TABS = (("markers", "1 Markers"), ("robots", "2 Robots"), ("stats", "3 Statistics"),
        ("map", "4 Map"), ("config", "5 Config"), ("log", "6 Log"), ("camera", "7 Camera"))
# States in which the shown data is not live: rows greyed, no frame rate, no robot "ok".
FROZEN_STATES = ("stale", "disconnected", "stopped", "connecting")
# The Camera tab renews its thumbnail lease this often, for this long (docs/protocol.md).
CAMERA_RENEW_S = 1.5
CAMERA_LEASE_S = 4.0
# Tables refresh at most this often. A refresh draws only the lines that changed, but on
# the Pi the UI shares the CPU (and, inside kmead, the GIL) with the pipeline: 4 Hz is
# plenty for a person.
UI_PERIOD_S = 0.25
# A live daemon's socket is drained once per repaint; while the UI is still busy with the
# last batch, again after this long (s); with nothing at all, once per ui_period.
DRAIN_RETRY_S = 0.02
# Topics whose bodies are decoded only when a shown pane needs them (the largest ones).
LAZY_TOPICS = (protocol.TOPIC_MARKERS, protocol.TOPIC_ROBOTS, protocol.TOPIC_STATS)
# event/log messages are a history, not a state: kept (not coalesced), up to this many
# per batch; older ones beyond it are dropped and counted.
EVENT_BACKLOG = 500


def terminal_has_16_colours(env: dict[str, str] | None = None) -> bool:
    """True when the terminal announces neither 256 colours nor truecolor."""
    env = dict(os.environ) if env is None else env
    if env.get("COLORTERM", "").lower() in ("truecolor", "24bit"):
        return False
    return "256" not in env.get("TERM", "")


def connection_state(ping_ok: bool | None, ping_detail: str, last_telemetry: float | None,
                     now: float, stale_after: float) -> tuple[str, str]:
    """(state, detail) of a daemon connection.

    ``disconnected``: the control ping fails; ``stale``: it answers but no telemetry came
    for ``stale_after`` s (or none yet); ``connected``; ``connecting`` before the first ping.
    Times are ``time.monotonic()`` seconds.
    """
    if ping_ok is None:
        return "connecting", ""
    if not ping_ok:
        return "disconnected", ping_detail or "control ping failed"
    if last_telemetry is None:
        return "stale", "no telemetry yet"
    age = now - last_telemetry
    if age > stale_after:
        return "stale", f"no telemetry for {age:.0f} s"
    return "connected", ""


def fusion_map_markers(status: dict[str, Any] | None) -> list[dict[str, Any]]:
    """A fusion node's map markers (status ``map.markers``) as the map draws markers: ids
    at their surveyed places, none detected (a fusion node sees through its cameras)."""
    out = []
    for m in ((status or {}).get("map") or {}).get("markers") or []:
        if (isinstance(m, list) and len(m) == 4
                and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in m)):
            out.append({"id": int(m[0]), "map_x": m[1], "map_y": m[2], "map_z": m[3],
                        "detected": False})
    return out


class KmeaTui(App[None]):
    """The UI. ``client`` is a :class:`DaemonClient` or a :class:`RecordingClient`."""

    CSS_PATH = "app.tcss"
    TITLE = "kmea-tui"
    BINDINGS = [
        *(Binding(str(i + 1), f"show_tab('{tab}')", title, show=False)
          for i, (tab, title) in enumerate(TABS)),
        # q quits outside text fields (an Input takes the letter); Ctrl+Q from anywhere.
        Binding("q", "quit", "Quit", show=False),
        Binding("ctrl+q", "quit", "Quit", key_display="^q", priority=True),
        Binding("escape", "leave_field", "Leave field", show=False),
        Binding("x", "reset_stats", "Reset stats"),
        Binding("plus,equals_sign", "magnify(1)", "Error ×"),
        Binding("minus", "magnify(-1)", "Error ÷"),
        Binding("a", "auto_magnification", "Auto ×"),
        Binding("question_mark", "toggle_help", "Help", show=False),
    ]

    def __init__(self, client: Client, *, theme: str | None = None,
                 ui_period: float = UI_PERIOD_S,
                 stale_after: float = 2.0, ping_period: float = 1.0) -> None:
        super().__init__()
        self.client = client
        if theme is None:
            theme = "ansi-dark" if terminal_has_16_colours() else "textual-dark"
        self.theme = theme
        self.ui_period = ui_period
        self.stale_after = stale_after
        self.ping_period = ping_period
        self.frame: dict[str, Any] | None = None
        self.status: dict[str, Any] | None = None
        # The last markers/robots/stats bodies (properties markers_body, ...), and those
        # received but not decoded yet.
        self._bodies: dict[str, dict[str, Any] | None] = {}
        self._raw_bodies: dict[str, list[bytes]] = {}
        # Tabs whose pane has not shown the last bodies yet (hidden tabs are not repainted).
        self._dirty: set[str] = set()
        self.received = 0
        self.coalesced = 0
        self.batches = 0
        self.replay_done = False
        self.ping_ok: bool | None = None
        self.ping_detail = ""
        self.role: str | None = None  # "viewer": the daemon serves this key read-only
        self.last_telemetry: float | None = None
        self.connection_state = "connecting"
        self.config_loaded = False
        self.daemon_stopped = False
        self.frozen = False
        self.camera_size: tuple[int, int] | None = None  # the frame size, from the status
        self.fusion_node = False  # the status says so: no markers, statistics or camera
        self._log_attached = False
        self._ui_ready = asyncio.Event()
        # Keys this UI set live (the daemon accepted them) since its last save_config: what
        # a quit would leave unsaved. Only the UI's own changes: it cannot know another
        # client's, and a key set back to its saved value still counts (it was not saved).
        self.unsaved: dict[str, object] = {}
        self._robots_at = 0.0  # time.monotonic() when the last robots body arrived
        self._quit_after_save = False

    # -- layout ----------------------------------------------------------------------------
    def compose(self) -> ComposeResult:
        with TabbedContent(initial="markers", id="tabs"):
            with TabPane(TABS[0][1], id="markers"):
                yield MarkersPane()
            with TabPane(TABS[1][1], id="robots"):
                yield RobotsPane()
            with TabPane(TABS[2][1], id="stats"):
                yield StatsPane()
            with TabPane(TABS[3][1], id="map"):
                yield MapPane()
            with TabPane(TABS[4][1], id="config"):
                yield ConfigPane(id="config-pane")
            with TabPane(TABS[5][1], id="log"):
                yield LogPane(id="log-pane")
            with TabPane(TABS[6][1], id="camera"):
                yield CameraPane(id="camera-pane")
        yield StatusBar(id="status")
        yield Footer()

    async def on_mount(self) -> None:
        self._ui_ready.set()
        await self.client.open()
        self.stream()
        if self.client.live:
            self.ping_loop()
            self.set_interval(0.5, self.update_connection_state)
        self.control("get_state")
        self.control("get_config")
        if self.client.live:
            self.control("get_log")  # what the daemon logged before we attached
        self.update_connection_state()
        self.query_one("#markers-table").focus()

    def on_unmount(self) -> None:
        self.workers.cancel_all()
        self.client.close()

    # -- the telemetry stream ----------------------------------------------------------------
    @work(exclusive=True, group="stream")
    async def stream(self) -> None:
        """Read telemetry, coalesce per topic, post at most one batch per ``ui_period``."""
        latest: dict[str, Any] = {}
        events: deque[tuple[str, dict[str, Any]]] = deque()
        received = coalesced = 0
        next_post = 0.0
        ended_sent = False
        # A live daemon: its socket is drained once per repaint (the messages wait in
        # ZeroMQ's queue meanwhile) rather than waking the UI for each of the ~100 a second,
        # and bodies are decoded only for the messages kept: the last of each topic, and
        # for the tables' topics only when a pane shows them (see _body).
        drain = getattr(self.client, "drain_raw", None)
        decode = getattr(self.client, "decode_raw", None)
        if drain is not None and decode is None:
            raise TypeError("a client with drain_raw needs decode_raw")
        while True:
            if drain is not None:
                wait = next_post - time.monotonic()
                if wait <= 0:  # the UI is still busy, or nothing came the last time
                    wait = DRAIN_RETRY_S if (latest or events) else self.ui_period
                await asyncio.sleep(wait)
                msgs = drain()
            else:
                msgs = await self.client.recv(0.05)
            now = time.monotonic()
            if msgs:
                self.last_telemetry = now
            for topic, body in msgs:
                received += 1
                if topic in (protocol.TOPIC_EVENT, protocol.TOPIC_LOG):
                    if decode is not None and drain is not None:
                        got = decode(body)
                        if got is None:
                            continue
                        body = got[1]
                    events.append((topic, body))
                    if len(events) > EVENT_BACKLOG:
                        events.popleft()
                        coalesced += 1
                    continue
                if topic in latest:
                    coalesced += 1
                latest[topic] = body
            ended = self.client.ended
            pending = bool(latest or events) or (ended and not ended_sent)
            if pending and now >= next_post and self._ui_ready.is_set():
                raw: dict[str, list[bytes]] = {}
                if decode is not None and drain is not None:
                    raw = {t: latest.pop(t) for t in LAZY_TOPICS if t in latest}
                    latest = {t: m[1] for t, f in latest.items()
                              if (m := decode(f)) is not None and m[0] == t}
                self._ui_ready.clear()
                self.post_message(TelemetryBatch(latest, list(events), received, coalesced,
                                                 ended=ended, raw=raw))
                ended_sent = ended
                latest, events = {}, deque()
                next_post = now + self.ui_period

    # The tables' bodies: kept as received (undecoded) until a pane needs them.
    def _body(self, topic: str) -> dict[str, Any] | None:
        frames = self._raw_bodies.pop(topic, None)
        if frames is not None:
            got = self.client.decode_raw(frames)  # type: ignore[union-attr]
            if got is not None and got[0] == topic:
                self._bodies[topic] = got[1]
        return self._bodies.get(topic)

    def _set_body(self, topic: str, body: dict[str, Any] | None) -> None:
        self._raw_bodies.pop(topic, None)
        self._bodies[topic] = body

    markers_body = property(lambda self: self._body(protocol.TOPIC_MARKERS),
                            lambda self, b: self._set_body(protocol.TOPIC_MARKERS, b))
    robots_body = property(lambda self: self._body(protocol.TOPIC_ROBOTS),
                           lambda self, b: self._set_body(protocol.TOPIC_ROBOTS, b))
    stats_body = property(lambda self: self._body(protocol.TOPIC_STATS),
                          lambda self, b: self._set_body(protocol.TOPIC_STATS, b))

    def on_telemetry_batch(self, msg: TelemetryBatch) -> None:
        try:
            self.apply_batch(msg)
        except NoMatches:
            pass  # shutting down: the widgets are gone, messages may still arrive
        finally:
            self._ui_ready.set()

    def apply_batch(self, msg: TelemetryBatch) -> None:
        """Store the batch's bodies and repaint only what is on screen: the status bar, the
        log (a history: every event is kept) and the active tab; a hidden tab is brought up
        to date when it is shown (:meth:`on_tabbed_content_tab_activated`)."""
        self.batches += 1
        self.received, self.coalesced = msg.received, msg.coalesced
        latest = msg.latest
        with self.batch_update():
            if (body := latest.get(protocol.TOPIC_FRAME)) is not None:
                self.frame = body
                self.daemon_stopped = False
            if (body := latest.get(protocol.TOPIC_STATUS)) is not None:
                self.show_status(body)
                self._dirty.add("map")
            if (body := latest.get(protocol.TOPIC_CAMERA)) is not None:
                try:
                    self.query_one(CameraPane).show_frame(CameraFrame.from_body(body))
                except FrameError as e:
                    self.query_one(CameraPane).show_caption(str(e), error=True)
            for topic, tabs in ((protocol.TOPIC_MARKERS, ("markers", "map")),
                                (protocol.TOPIC_ROBOTS, ("robots", "map")),
                                (protocol.TOPIC_STATS, ("stats",))):
                if (body := latest.get(topic)) is not None:
                    self._set_body(topic, body)
                elif (frames := msg.raw.get(topic)) is not None:
                    self._raw_bodies[topic] = frames
                else:
                    continue
                if topic == protocol.TOPIC_ROBOTS:
                    self._robots_at = time.monotonic()
                self._dirty.update(tabs)
            if msg.events:
                self.query_one(LogPane).add_events(msg.events)
            self.show_tab_data(self.query_one(TabbedContent).active)
            if msg.ended:
                self.replay_done = True
            self.update_connection_state()

    def show_tab_data(self, tab: str) -> None:
        """Bring tab ``tab``'s pane up to date with the last bodies, if they changed."""
        if tab not in self._dirty:
            return
        self._dirty.discard(tab)
        if tab == "markers" and self.markers_body is not None:
            self.query_one(MarkersPane).update_markers(self.markers_body)
        elif tab == "robots" and self.robots_body is not None:
            self._show_robots()
        elif tab == "stats" and self.stats_body is not None:
            self.query_one(StatsPane).update_stats(self.stats_body)
        elif tab == "map":
            markers = (self.markers_body or {}).get("markers", [])
            if not markers and self.fusion_node:
                markers = fusion_map_markers(self.status)
            self.query_one(MapPane).set_data(MapData(
                markers=markers, robots=(self.robots_body or {}).get("robots", []),
                moved=moved_ids(markers)))

    def show_status(self, body: dict[str, Any]) -> None:
        """The daemon's ``status``: logging/recording state and the algorithms it offers;
        its shutdown (``state`` stopped); the camera's frame size (for the Camera tab)."""
        self.status = body
        # The daemon announces its end: say so rather than show frozen data.
        self.daemon_stopped = body.get("state") == "stopped"
        cam = body["camera"]
        self.camera_size = (cam["width"], cam["height"])
        extent = body.get("map", {}).get("extent")
        if isinstance(extent, list) and len(extent) == 4 and all(
                isinstance(v, (int, float)) and math.isfinite(v) for v in extent):
            floor = self.query_one(FloorMap)
            if floor.outline != tuple(extent):
                floor.outline = tuple(float(v) for v in extent)
                floor.refresh()
        if "fusion" in body and not self.fusion_node:
            self._became_fusion_node()
        self.query_one(LogPane).update_status(body)
        if isinstance(body.get("inputs"), list):  # a fusion node's cameras and clocks
            self.query_one(RobotsPane).inputs = body["inputs"]
        self.query_one(ConfigPane).set_algorithms(body["algorithms"])
        bar = self.query_one(StatusBar)
        alert = output_alert(body)
        overlay = any(str(f).endswith(".local.toml") for f in body.get("config_files", []))
        if alert != bar.alert or overlay != bar.overlay:
            bar.alert, bar.overlay = alert, overlay
            bar.show(bar.state, None, bar.detail)

    def _became_fusion_node(self) -> None:
        """A fusion node has robots, no markers, statistics or camera: say so in those
        tabs and open on Robots (unless the user already chose a tab)."""
        self.fusion_node = True
        note = "a fusion node has no {}: its robots are on 2 Robots and 4 Map"
        self.query_one("#markers-summary", Static).update(note.format("markers"))
        self.query_one("#stats-summary", Static).update(note.format("marker statistics"))
        self.query_one(CameraPane).show_caption("camera: not available on a fusion node "
                                                "(no camera)")
        self.query_one(ConfigPane).show_fusion_node()
        self.refresh_bindings()  # no "Reset stats"
        if self.query_one(TabbedContent).active == "markers":
            self.action_show_tab("robots")

    # -- connection state ----------------------------------------------------------------------
    @work(exclusive=True, group="ping")
    async def ping_loop(self) -> None:
        if not self.client.control:
            # No control socket (network.control = ""): judge by telemetry alone.
            self.post_message(ConnectionChanged(True, "control socket off"))
            return
        while True:
            reply = await self.client.request("ping", timeout=min(0.5, self.ping_period))
            ok = bool(reply.get("ok"))
            role = reply.get("role") if isinstance(reply.get("role"), str) else None
            if ok != self.ping_ok or (ok and role != self.role):
                self.post_message(ConnectionChanged(ok, str(reply.get("error", "")), role))
            await asyncio.sleep(self.ping_period)

    def on_connection_changed(self, msg: ConnectionChanged) -> None:
        with suppress(NoMatches):  # shutting down
            self._connection_changed(msg)

    def _connection_changed(self, msg: ConnectionChanged) -> None:
        was = self.ping_ok
        self.ping_ok, self.ping_detail = msg.ok, msg.detail
        if msg.ok:
            self.role = msg.role
        if (msg.ok and was is False) or (msg.ok and not self.config_loaded):
            # (Re)connected: the daemon may have restarted with another configuration.
            self.control("get_state")
            self.control("get_config")
        if was is not None:
            self.query_one(LogPane).note(
                f"daemon {'reachable again' if msg.ok else 'not answering'} "
                f"({self.client.control})", msg.ok)
        self.update_connection_state()

    def compute_state(self, now: float | None = None) -> tuple[str, str]:
        if not self.client.live:
            return ("replay end" if self.replay_done else "replay"), self.client.name
        if self.daemon_stopped:
            return "stopped", "the daemon announced its shutdown"
        return connection_state(self.ping_ok, self.ping_detail, self.last_telemetry,
                                time.monotonic() if now is None else now, self.stale_after)

    def update_connection_state(self) -> None:
        state, detail = self.compute_state()
        bad = getattr(self.client, "bad_messages", 0)
        if state == "stale" and bad:
            # Telemetry arrives but is not understood (e.g. another protocol version).
            detail = f"{bad} messages not understood: {getattr(self.client, 'last_error', '')}"
        self.connection_state = state
        frozen = state in FROZEN_STATES
        with suppress(NoMatches, ScreenStackError):  # shutting down
            self.query_one(StatusBar).show(state, self.frame, detail,
                                           read_only=self.role == "viewer")
            if frozen != self.frozen:
                self._set_frozen(frozen)
            elif frozen and self.query_one(TabbedContent).active == "robots":
                self._show_robots()  # the ages keep growing while nothing arrives

    def _show_robots(self) -> None:
        """The Robots tab from the last body. Not live, each robot's age grows from its
        last known fix on this machine's clock (the time since the body arrived), so a
        technician sees how old the pose really is; the daemon's clock is not used (a
        remote daemon's may differ, a replayed source's is the recording's)."""
        if self.robots_body is not None:
            self.query_one(RobotsPane).update_robots(
                self.robots_body, since=time.monotonic() - self._robots_at)

    def _set_frozen(self, frozen: bool) -> None:
        """Grey the data and stop claiming it is live (or undo that)."""
        self.frozen = frozen
        self.screen.set_class(frozen, "-frozen")
        self.query_one(RobotsPane).frozen = frozen
        self._show_robots()
        self.query_one(CameraPane).set_dim(frozen)

    # -- control -------------------------------------------------------------------------------
    def control(self, cmd: str, **args: Any) -> None:
        """Send ``cmd`` in the background; the reply comes back as a :class:`ControlReply`."""
        self.run_worker(self._control(cmd, args), group="control")

    async def _control(self, cmd: str, args: dict[str, Any]) -> None:
        reply = await self.client.request(cmd, **args)
        self.post_message(ControlReply(cmd, args, reply))

    def on_control_request(self, msg: ControlRequest) -> None:
        msg.stop()
        self.control(msg.cmd, **msg.args)

    def on_control_reply(self, msg: ControlReply) -> None:
        with suppress(NoMatches):  # shutting down
            self._control_reply(msg)

    def _control_reply(self, msg: ControlReply) -> None:
        cmd, args, reply = msg.cmd, msg.args, msg.reply
        ok = bool(reply.get("ok"))
        config_pane = self.query_one(ConfigPane)
        log_pane = self.query_one(LogPane)
        error = str(reply.get("error", "failed"))
        if cmd == "get_state":
            # The daemon's last status and frame: show them before the next telemetry.
            if ok and isinstance(reply.get("status"), dict) and self.status is None:
                self.show_status(reply["status"])
            return
        if cmd == "get_config":
            if ok and isinstance(reply.get("config"), dict):
                self.config_loaded = True
                overlay = reply.get("overlay_file")
                adv = reply.get("advanced")
                config_pane.advanced = {str(k) for k in adv} if isinstance(adv, list) else set()
                config_pane.show_config(
                    reply["config"],
                    save_target=(f"{overlay} (changed keys only; read at the next start)"
                                 if overlay else None),
                    source=reply.get("config_file")
                    or ", ".join(map(str, reply.get("config_files") or [])) or None)
            elif args:
                config_pane.show_reply(f"get_config: {error}", False)
            return
        if cmd == "get_log":
            if ok and isinstance(reply.get("lines"), list) and not self._log_attached:
                self._log_attached = True
                lines = [ln for ln in reply["lines"] if isinstance(ln, dict)]
                log_pane.note(f"the daemon's last {len(lines)} log lines (before this UI "
                              "attached):", True)
                log_pane.add_events([("log", ln) for ln in lines])
            return
        if cmd == "camera_watch":
            if not ok:
                self.query_one(CameraPane).show_caption(f"camera: {error}", error=True)
            elif reply.get("images") is False:
                self.query_one(CameraPane).show_caption(
                    "camera: this source has no images (a replay of detections)", error=True)
            return
        if cmd == "snapshot":
            text = (f"snapshot saved: {reply.get('path')}" if ok else f"snapshot: {error}")
            log_pane.note(text, ok)
            self.query_one(CameraPane).show_caption(text, error=not ok)
            self.notify(text, severity="information" if ok else "error")
            return
        if cmd == "set":
            text = f"{args.get('key')} = {args.get('value')!r}"
            config_pane.show_reply(f"set {text}" if ok else f"set {text}: {error}", ok)
            if ok:
                self.unsaved[str(args.get("key"))] = args.get("value")
                self.control("get_config")
            else:
                config_pane.revert(str(args.get("key", "")))
            self.notify(f"set {args.get('key')}" + ("" if ok else f": {error}"),
                        severity="information" if ok else "error")
            return
        if cmd == "save_config":
            where = reply.get("path") or reply.get("file") or config_pane.save_target
            config_pane.show_reply(f"saved to {where}" if ok else f"save: {error}", ok)
            self.notify(f"configuration saved to {where}" if ok else f"save failed: {error}",
                        severity="information" if ok else "error")
            if ok:
                # Keys still on trial ("held") are saved again by the daemon once their
                # trial passes (or at its shutdown): nothing is left for the user to do.
                self.unsaved.clear()
                if self._quit_after_save:
                    self.exit()
            self._quit_after_save = False
            return
        if cmd in ("log_start", "log_stop", "record_start", "record_stop", "reload_map",
                   "reset_stats"):
            path = reply.get("path")
            text = f"{cmd}" + (f" {path}" if path else "") + ("" if ok else f": {error}")
            log_pane.note(text, ok)
            if cmd in ("reload_map",):
                config_pane.show_reply(text, ok)
            self.notify(text, severity="information" if ok else "error")

    # -- key actions -------------------------------------------------------------------------
    async def action_quit(self) -> None:
        """q / Ctrl+Q: quit at once, unless this UI's live changes were never saved: then
        ask once (quit anyway, save and quit, cancel); q or Ctrl+Q again quits."""
        if not self.unsaved or isinstance(self.screen, QuitScreen):
            self.exit()
            return
        self.push_screen(QuitScreen(list(self.unsaved)), self._quit_answer)

    def _quit_answer(self, answer: str | None) -> None:
        if answer == "quit":
            self.exit()
        elif answer == "save":
            self._quit_after_save = True  # quits on the save's reply, stays if it fails
            self.control("save_config")

    def check_action(self, action: str, parameters: tuple[object, ...]) -> bool | None:
        if isinstance(self.screen, QuitScreen):
            return action == "quit"  # the question is open: no tab switching under it
        tab = self.query_one(TabbedContent).active if self.is_mounted else ""
        if action == "leave_field":
            return isinstance(self.focused, (Input, Select))
        if action == "reset_stats":  # a fusion node has no marker statistics to reset
            return tab == "stats" and not self.fusion_node
        if action in ("magnify", "auto_magnification"):
            return tab == "map"
        return True

    def on_tabbed_content_tab_activated(self, event: TabbedContent.TabActivated) -> None:
        if not self.screen_stack:  # a tab's activation still queued while the app closes
            return
        with suppress(NoMatches):
            self.show_tab_data(self.query_one(TabbedContent).active)
        self.refresh_bindings()
        if event.pane.id == "camera" and self.fusion_node:
            pass  # nothing to watch; the caption says so
        elif event.pane.id == "camera" and self.client.live:
            self.camera_watch_loop()
        elif event.pane.id == "camera":
            self.query_one(CameraPane).show_caption(
                f"camera: no images when replaying {self.client.name}")
        else:
            self.workers.cancel_group(self, "camera")  # the lease runs out by itself

    @work(exclusive=True, group="camera")
    async def camera_watch_loop(self) -> None:
        """While the Camera tab is shown: renew the daemon's thumbnail lease, sized to
        the pane (the daemon sends nothing to a UI that does not watch)."""
        while True:
            view = self.query_one(CameraPane).view
            cols, rows = view.size.width or 78, view.size.height or 18
            fw, fh = self.camera_size or (640, 480)
            w, h = display_size(fw, fh, cols, rows, view.braille)
            reply = await self.client.request("camera_watch", width=w, height=h,
                                              lease_s=CAMERA_LEASE_S)
            self.post_message(ControlReply("camera_watch", {}, reply))
            await asyncio.sleep(CAMERA_RENEW_S)

    def action_leave_field(self) -> None:
        """Escape: out of a text field or list, back to the tab's main widget (so q and
        the tab numbers are keys again, not text)."""
        tab = self.query_one(TabbedContent).active
        target = {"config": "#config-pane", "log": "#events"}.get(tab)
        if target is None:
            self.action_show_tab(tab)
        else:
            self.query_one(target).focus()

    def action_show_tab(self, tab: str) -> None:
        self.query_one(TabbedContent).active = tab
        focus = {"markers": "#markers-table", "robots": "#robots-table",
                 "stats": "#stats-table", "map": FloorMap, "config": "#algorithm",
                 "log": "#events", "camera": "#camera-view"}[tab]
        self.query_one(focus).focus()  # type: ignore[call-overload]
        self.refresh_bindings()

    def action_toggle_help(self) -> None:
        """Textual's help panel: the focused widget's HELP (e.g. the markers' flags), keys."""
        if self.screen.query(HelpPanel):
            self.action_hide_help_panel()
        else:
            self.action_show_help_panel()

    def action_reset_stats(self) -> None:
        self.control("reset_stats")

    def action_magnify(self, step: int) -> None:
        self.query_one(MapPane).change_magnification(step)

    def action_auto_magnification(self) -> None:
        self.query_one(MapPane).auto_magnification()

    def on_live_table_sort_changed(self, event: LiveTable.SortChanged) -> None:
        # Robots and statistics summaries show the sort; re-render them from the last data.
        self._show_robots()


async def save_screenshots(recording: str | Path, out_dir: str | Path,
                           size: tuple[int, int] = (80, 24),
                           theme: str = "textual-dark") -> list[Path]:
    """SVG of every tab after replaying ``recording`` at once: ``out_dir/tui-TAB.svg``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    app = KmeaTui(RecordingClient(recording), theme=theme)
    files: list[Path] = []
    async with app.run_test(size=size) as pilot:
        for _ in range(1000):
            if app.replay_done and app.config_loaded:
                break
            await pilot.pause(0.01)
        for i, (tab, _) in enumerate(TABS):
            await pilot.press(str(i + 1))
            await pilot.pause(0.1)
            path = out / f"tui-{tab}.svg"
            path.write_text(app.export_screenshot(title=f"kmea-tui: {tab}"), encoding="utf-8")
            files.append(path)
    return files

