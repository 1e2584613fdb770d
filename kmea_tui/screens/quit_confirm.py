"""Asked once when quitting with live changes that were never saved."""

from __future__ import annotations

from rich.text import Text
from textual import on
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical
from textual.screen import ModalScreen
from textual.widgets import Button, Static


def unsaved_text(keys: list[str], limit: int = 4) -> str:
    """``filter.alpha, robots`` (and ``+N more`` beyond ``limit``)."""
    shown = ", ".join(keys[:limit])
    return shown + (f" +{len(keys) - limit} more" if len(keys) > limit else "")


class QuitScreen(ModalScreen[str]):
    """Returns "quit", "save" (save, then quit) or "cancel"."""

    # q again quits: the same key that asked, so a technician who meant it is not slowed.
    BINDINGS = [Binding("q", "answer('quit')", "Quit anyway"),
                Binding("s", "answer('save')", "Save and quit"),
                Binding("escape,c", "answer('cancel')", "Cancel")]

    def __init__(self, keys: list[str]) -> None:
        super().__init__()
        self.keys = keys

    def compose(self) -> ComposeResult:
        with Vertical(id="quit-dialog"):
            yield Static(f"Live changes not saved: {unsaved_text(self.keys)}", id="quit-keys",
                         classes="form-title", markup=False)
            yield Static("They are lost when kmead restarts unless saved.", classes="note")
            with Horizontal(classes="form-row"):
                yield Button(Text("Quit anyway [q]"), id="quit-anyway", variant="error")
                yield Button(Text("Save and quit [s]"), id="quit-save", variant="primary")
                yield Button(Text("Cancel [Esc]"), id="quit-cancel")

    def on_mount(self) -> None:
        self.query_one("#quit-cancel", Button).focus()

    def action_answer(self, answer: str) -> None:
        self.dismiss(answer)

    @on(Button.Pressed)
    def _pressed(self, event: Button.Pressed) -> None:
        self.dismiss({"quit-anyway": "quit", "quit-save": "save"}.get(
            event.button.id or "", "cancel"))
