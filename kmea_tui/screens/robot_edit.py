"""Modal form to add or edit one robot of the configuration."""

from __future__ import annotations

from typing import Any

from textual import on
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical
from textual.screen import ModalScreen
from textual.widgets import Button, Input, Label, Static

DEFAULT_HEIGHT = 0.20
DEFAULT_LENGTH = 0.06
DEFAULT_SEPARATION = 0.10


def parse_robot(name: str, markers: str, height: str, length: str,
                destinations: str, separation: str = "") -> dict[str, Any]:
    """A robot table from the form's text; ``ValueError`` names the bad field.

    ``markers``: one id (``42``) or a pair left,right (``40,41`` or ``40+41``);
    ``separation``: distance between a pair's marker centres (m).
    """
    name = name.strip()
    if not name or any(c.isspace() for c in name):
        raise ValueError("name: give a name without spaces")
    parts = [p for p in markers.replace("+", ",").replace(" ", ",").split(",") if p]
    try:
        ids = [int(p) for p in parts]
    except ValueError:
        raise ValueError(f"markers: {markers!r} is not one id or a pair of ids") from None
    if len(ids) not in (1, 2) or any(i < 0 for i in ids) or len(set(ids)) != len(ids):
        raise ValueError(f"markers: {markers!r} is not one id or a pair of different ids")
    out: dict[str, Any] = {"name": name, "markers": ids}
    for field, text, default in (("height", height, DEFAULT_HEIGHT),
                                 ("length", length, DEFAULT_LENGTH),
                                 ("separation", separation, DEFAULT_SEPARATION)):
        try:
            v = float(text) if text.strip() else default
        except ValueError:
            raise ValueError(f"{field}: {text!r} is not a number of metres") from None
        if (field in ("length", "separation") and v <= 0) or v < 0:
            raise ValueError(f"{field}: must be positive (metres)")
        out[field] = v
    out["destinations"] = [d.strip() for d in destinations.split(",") if d.strip()]
    return out


class RobotEditScreen(ModalScreen[dict[str, Any] | None]):
    """Returns the robot's table, or None when cancelled."""

    BINDINGS = [Binding("escape", "cancel", "Cancel")]

    def __init__(self, robot: dict[str, Any] | None) -> None:
        super().__init__()
        self.robot = robot or {}

    def compose(self) -> ComposeResult:
        r = self.robot
        markers = r.get("markers", [])
        markers_s = ",".join(map(str, markers)) if isinstance(markers, list) else str(markers)
        with Vertical(id="robot-dialog"):
            yield Static("Edit robot" if r else "Add robot", classes="form-title")
            for key, label, value, hint in (
                ("name", "name", r.get("name", ""), "amr3"),
                ("markers", "markers", markers_s, "42 or left,right e.g. 40,41"),
                ("height", "height m", str(r.get("height", DEFAULT_HEIGHT)), "plate height"),
                ("length", "length m", str(r.get("length", DEFAULT_LENGTH)), "marker side"),
                ("separation", "separation m", str(r.get("separation", DEFAULT_SEPARATION)),
                 "pair: distance between the marker centres"),
                ("destinations", "destinations", ", ".join(r.get("destinations", []) or []),
                 "udp host:port, comma separated"),
            ):
                with Horizontal(classes="form-row"):
                    yield Label(label, classes="form-label")
                    yield Input(str(value), placeholder=hint, id=f"robot-{key}", compact=True)
            yield Static("", id="robot-error", classes="error")
            with Horizontal(classes="form-row"):
                yield Button("OK", id="robot-ok", variant="primary")
                yield Button("Cancel", id="robot-cancel")

    def _value(self, key: str) -> str:
        return self.query_one(f"#robot-{key}", Input).value

    @on(Button.Pressed, "#robot-ok")
    @on(Input.Submitted)
    def _ok(self) -> None:
        try:
            robot = parse_robot(*(self._value(k) for k in
                                  ("name", "markers", "height", "length", "destinations",
                                   "separation")))
        except ValueError as e:
            self.query_one("#robot-error", Static).update(str(e))
            return
        # Keep keys the form does not show (the daemon may have more).
        self.dismiss({**self.robot, **robot})

    @on(Button.Pressed, "#robot-cancel")
    def action_cancel(self) -> None:
        self.dismiss(None)
