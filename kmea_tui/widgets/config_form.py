"""Configuration tab: algorithm, filter, robots and detector options, applied live."""

from __future__ import annotations

import json
from typing import Any

from rich.text import Text
from textual import on
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical, VerticalScroll
from textual.widgets import Button, DataTable, Input, Label, Select, Static

from kmea.wire.tomlvalue import parse_toml_value
from kmea_tui.messages import ControlRequest


def parse_value(text: str) -> Any:
    """A typed-in value as TOML (``1.0``, ``true``, ``"DICT_6X6_250"``, ``[1, 2]``);
    a bare word that is not TOML is taken as a string."""
    return parse_toml_value(text)  # the one reader, shared with kmead --set


def show_value(value: Any) -> str:
    """``value`` in TOML syntax (inline tables for dicts), as :func:`parse_value` reads it."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, dict):
        inner = ", ".join(f"{k} = {show_value(v)}" for k, v in value.items())
        return f"{{ {inner} }}" if inner else "{}"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(show_value(v) for v in value) + "]"
    return str(value)


# What a technician must know before choosing an estimator live (docs/speed.md).
ALGORITHM_NOTES = {"kmea-robust": "slow: ~0.3 s a frame, 2-3 frames/s"}

# Keys whose empty value means a default: the field is left empty and says which.
DEFAULT_TEXT = {"dictionary": "the map's dictionary (empty = the map's)"}


def _field_text(key: str, value: Any) -> str:
    return "" if key in DEFAULT_TEXT and value == "" else show_value(value)


def robot_row(r: dict[str, Any]) -> tuple[str, ...]:
    markers = r.get("markers")
    if isinstance(markers, list):
        markers_s = "+".join(map(str, markers))
    else:
        markers_s = str(markers)
    dests = r.get("destinations") or []
    sep = r.get("separation")
    return (str(r.get("name", "?")), markers_s, f"{float(r.get('height', 0.0)):.3f}",
            f"{float(r.get('length', 0.0)):.3f}",
            f"{float(sep):.3f}" if isinstance(markers, list) and len(markers) == 2
            and isinstance(sep, (int, float)) else "-",
            ", ".join(map(str, dests)) if isinstance(dests, list) else str(dests))


class RobotsConfigTable(DataTable):
    BINDINGS = [
        Binding("a", "add", "Add robot"),
        Binding("e,enter", "edit", "Edit"),
        Binding("d,delete", "remove", "Remove"),
    ]

    def on_mount(self) -> None:
        self.cursor_type = "row"
        for key, label in (("name", "name"), ("markers", "markers"), ("height", "height m"),
                           ("length", "length m"), ("separation", "pair sep m"),
                           ("destinations", "destinations")):
            self.add_column(label, key=key)

    def action_add(self) -> None:
        self.app.query_one(ConfigPane).edit_robot(None)

    def action_edit(self) -> None:
        if self.row_count:
            self.app.query_one(ConfigPane).edit_robot(self.cursor_row)

    def action_remove(self) -> None:
        if self.row_count:
            self.app.query_one(ConfigPane).remove_robot(self.cursor_row)


class ConfigPane(VerticalScroll):
    """Shows the daemon's effective configuration; every change is one control ``set``."""

    BINDINGS = [Binding("ctrl+s", "save", "Save config"),
                Binding("ctrl+r", "refresh_config", "Re-read")]

    def __init__(self, id: str | None = None) -> None:
        super().__init__(id=id)
        self.config: dict[str, Any] = {}
        # The daemon's estimators (its ``status`` telemetry), never a local registry.
        self.algorithms: list[str] = []
        self.robots: list[dict[str, Any]] = []
        self.save_target = "the daemon's configuration file"

    fusion_node = False  # set by show_fusion_node
    advanced: set[str] = set()  # section.key the daemon calls advanced (get_config)

    def compose(self) -> ComposeResult:
        yield Static("configuration not loaded yet (daemon not reachable?)", id="config-status",
                     classes="summary")
        # Where Save writes, near the top so it is visible at 80x24 (long paths wrap).
        yield Static("", id="save-note", classes="note", markup=False)
        with Horizontal(classes="form-row camera-only"):
            yield Label("algorithm", classes="form-label")
            yield Select([(a, a) for a in self.algorithms], allow_blank=True,
                         id="algorithm", prompt="(unknown)", compact=True)
        with Horizontal(classes="form-row camera-only"):
            yield Label("filter alpha", classes="form-label")
            yield Input(placeholder="0..1, 1 = no filtering", id="filter-alpha", compact=True)
        yield Label("robots: a add · e/Enter edit · d remove", classes="form-title",
                    markup=False)
        yield RobotsConfigTable(id="robots-config")
        yield Label("detector options (values in TOML syntax)", classes="form-title camera-only",
                    markup=False)
        yield Vertical(id="detector-options", classes="camera-only")
        with Horizontal(classes="form-row"):
            yield Button(Text("Save [ctrl+s]"), id="save", variant="primary")
            yield Button(Text("Re-read [ctrl+r]"), id="reread")
            yield Button("Reload map", id="reload-map", classes="camera-only")

    def show_fusion_node(self) -> None:
        """A fusion node has no camera: no estimator, detector, IIR filter or map to reload
        (it answers ``set`` of relay.* and log.level only)."""
        self.fusion_node = True
        for w in self.query(".camera-only"):
            w.display = False
        self.query_one("#save-note", Static).update(
            "a fusion node: no estimator, detector or camera settings (relay.* and "
            "log.level can be set live)")

    # -- showing the daemon's configuration ----------------------------------------------
    def set_algorithms(self, algorithms: list[str]) -> None:
        """The algorithms the daemon offers (``status.algorithms``)."""
        if list(algorithms) == self.algorithms:
            return
        self.algorithms = list(algorithms)
        self._show_algorithm()

    def _show_algorithm(self) -> None:
        est = self.config.get("estimator", {})
        algo = est.get("algorithm") if isinstance(est, dict) else None
        options = list(self.algorithms)
        if isinstance(algo, str) and algo not in options:
            options.append(algo)  # the running one, before the first status arrives
        select = self.query_one("#algorithm", Select)
        with select.prevent(Select.Changed):
            select.set_options([(f"{a} ({ALGORITHM_NOTES[a]})" if a in ALGORITHM_NOTES else a, a)
                                for a in options])
            if isinstance(algo, str):
                select.value = algo

    def show_config(self, config: dict[str, Any], save_target: str | None = None,
                    source: str | None = None) -> None:
        self.config = config
        if save_target:
            self.save_target = save_target
        self._show_algorithm()
        filt = config.get("filter", {}) if isinstance(config.get("filter"), dict) else {}
        alpha = self.query_one("#filter-alpha", Input)
        if not alpha.has_focus and "alpha" in filt:
            alpha.value = show_value(filt["alpha"])
        robots = config.get("robots", [])
        self.robots = [dict(r) for r in robots if isinstance(r, dict)]
        table = self.query_one(RobotsConfigTable)
        table.clear()  # a configuration change, not live data: small and rare
        for i, r in enumerate(self.robots):
            table.add_row(*robot_row(r), key=str(i))
        self._show_detector(config.get("detector", {}))
        if not self.fusion_node:
            self.query_one("#save-note", Static).update(f"Save writes {self.save_target}")
        self.query_one("#config-status", Static).update(Text.assemble(
            ("configuration", "bold"), f" ({source or 'the daemon'}): ",
            "Enter applies a value live; Save makes changes permanent"))

    def _show_detector(self, detector: Any) -> None:
        box = self.query_one("#detector-options", Vertical)
        # Advanced keys (the daemon's list) stay out of the form: --set and files set them.
        options = {k: v for k, v in (detector or {}).items()
                   if isinstance(v, (str, int, float, bool, dict, list))
                   and f"detector.{k}" not in self.advanced}
        existing = {inp.name for inp in box.query(Input)}
        if existing == set(options):
            for inp in box.query(Input):
                if not inp.has_focus and inp.name in options:
                    inp.value = _field_text(inp.name or "", options[inp.name])
            return
        box.remove_children()
        rows = []
        for key, value in options.items():
            rows.append(Horizontal(Label(key, classes="form-label"),
                                   Input(_field_text(key, value), name=key,
                                         placeholder=DEFAULT_TEXT.get(key, ""),
                                         id=f"detector-{key.replace('_', '-')}",
                                         classes="detector-option", compact=True),
                                   classes="form-row"))
        box.mount_all(rows)

    def revert(self, key: str) -> None:
        """Put the current value back in the field of ``key`` (after a refused ``set``)."""
        section, _, name = key.partition(".")
        value = (self.config.get(section) or {}).get(name) \
            if isinstance(self.config.get(section), dict) else None
        if value is None:
            return
        if key == "filter.alpha":
            inputs = [self.query_one("#filter-alpha", Input)]
        elif section == "detector":
            inputs = [inp for inp in self.query_one("#detector-options", Vertical).query(Input)
                      if inp.name == name]
        else:
            inputs = []
        for inp in inputs:
            inp.value = show_value(value)
            inp.cursor_position = len(inp.value)
        if key == "estimator.algorithm":
            select = self.query_one("#algorithm", Select)
            with select.prevent(Select.Changed):
                select.value = value

    def show_reply(self, text: str, ok: bool) -> None:
        self.query_one("#config-status", Static).update(
            Text(("✓ " if ok else "✗ ") + text, style="green" if ok else "bold red"))

    # -- user actions ------------------------------------------------------------------------
    def _set(self, key: str, value: Any) -> None:
        self.post_message(ControlRequest("set", {"key": key, "value": value}))

    @on(Select.Changed, "#algorithm")
    def _algorithm_changed(self, event: Select.Changed) -> None:
        if isinstance(event.value, str):
            self._set("estimator.algorithm", event.value)

    @on(Input.Submitted, "#filter-alpha")
    def _alpha_submitted(self, event: Input.Submitted) -> None:
        value = parse_value(event.value)
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            self.show_reply(f"filter alpha must be a number, got {event.value!r}", False)
            self.revert("filter.alpha")
            return  # nothing was applied: the field keeps the focus for a correction
        self._set("filter.alpha", float(value))
        self._leave_field()

    @on(Input.Submitted, ".detector-option")
    def _detector_submitted(self, event: Input.Submitted) -> None:
        self._set(f"detector.{event.input.name}", parse_value(event.value))
        self._leave_field()

    def _leave_field(self) -> None:
        # The value is on its way: back to the tab, as Escape does, so the digits switch
        # tabs and q quits again instead of being typed into the field. (A refused value
        # comes back into the field by itself, with the daemon's reason above.)
        self.focus()

    @on(Button.Pressed, "#save")
    def action_save(self) -> None:
        self.post_message(ControlRequest("save_config", {}))

    @on(Button.Pressed, "#reread")
    def action_refresh_config(self) -> None:
        self.post_message(ControlRequest("get_config", {}))

    @on(Button.Pressed, "#reload-map")
    def _reload_map(self) -> None:
        self.post_message(ControlRequest("reload_map", {}))

    def edit_robot(self, index: int | None) -> None:
        from kmea_tui.screens.robot_edit import RobotEditScreen

        robot = self.robots[index] if index is not None and index < len(self.robots) else None

        def done(result: dict[str, Any] | None) -> None:
            if result is None:
                return
            robots = [dict(r) for r in self.robots]
            if index is None or index >= len(robots):
                robots.append(result)
            else:
                robots[index] = result
            self._set("robots", robots)

        self.app.push_screen(RobotEditScreen(robot), done)

    def remove_robot(self, index: int) -> None:
        if 0 <= index < len(self.robots):
            robots = [dict(r) for i, r in enumerate(self.robots) if i != index]
            self._set("robots", robots)
