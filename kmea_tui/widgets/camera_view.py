"""The camera thumbnail as text: greyscale in half blocks (or braille dots) scaled to the
pane, marker outlines with their ids, suspect markers marked, map markers the camera should
see but does not, and the focus figure.

:func:`render_camera` is pure (a :class:`CameraFrame` and a cell size in, rows of Rich text
out); :class:`CameraView` is the widget that shows it. Image pixels: x right, y down.
Corners come in full-frame pixels and are scaled here, so the outline stays on the marker
whatever the thumbnail size.
"""

from __future__ import annotations

import base64
import math
from dataclasses import dataclass, field
from typing import Any

from rich.color import Color
from rich.segment import Segment
from rich.style import Style
from rich.text import Text
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Vertical
from textual.strip import Strip
from textual.widget import Widget
from textual.widgets import Static

from kmea_tui.canvas import BrailleCanvas
from kmea_tui.messages import ControlRequest

# Outline styles: the 16 ANSI colours, so they read the same on any terminal.
KIND_COLOR = {"detected": "bright_green", "suspect": "bright_yellow", "rejected": "bright_red",
              "expected": "bright_cyan"}
KINDS = tuple(KIND_COLOR)
MAX_PIXELS = 640 * 480  # a thumbnail larger than this is refused (hostile input)
HALF_BLOCK = "▀"


class FrameError(ValueError):
    """A thumbnail body that cannot be shown; the text names the field."""


@dataclass
class CameraMarker:
    """One outline: id, corners (4 (x, y) pairs, full-frame pixels), kind (see KINDS)."""

    id: int
    corners: list[tuple[float, float]]
    kind: str = "detected"


@dataclass
class CameraFrame:
    """A greyscale thumbnail and what to draw on it.

    width, height: thumbnail size; pixels: ``width * height`` bytes, row-major grey.
    full_width, full_height: the camera frame the marker corners refer to.
    focus: sharpness of the marker regions (variance of the Laplacian), or None.
    """

    width: int
    height: int
    pixels: bytes
    full_width: int
    full_height: int
    markers: list[CameraMarker] = field(default_factory=list)
    focus: float | None = None
    frame: int | None = None
    t: float | None = None

    @classmethod
    def from_body(cls, body: dict[str, Any]) -> CameraFrame:
        """Parse a ``camera`` telemetry body (see docs/protocol.md); ``FrameError``."""

        def integer(key: str, lo: int, hi: int) -> int:
            v = body.get(key)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise FrameError(f"camera: field {key!r} must be an integer {lo}..{hi}")
            return v

        w, h = integer("width", 1, 4096), integer("height", 1, 4096)
        if w * h > MAX_PIXELS:
            raise FrameError(f"camera: thumbnail {w}x{h} larger than {MAX_PIXELS} pixels")
        fw, fh = integer("full_width", 1, 100000), integer("full_height", 1, 100000)
        if body.get("encoding") != "gray8":
            raise FrameError("camera: field 'encoding' must be 'gray8'")
        try:
            pixels = base64.b64decode(body.get("data") or "", validate=True)
        except (ValueError, TypeError):
            raise FrameError("camera: field 'data' is not base64") from None
        if len(pixels) != w * h:
            raise FrameError(f"camera: field 'data' holds {len(pixels)} bytes, "
                             f"expected {w * h}")
        markers = []
        for i, m in enumerate(body.get("markers") or []):
            try:
                corners = [(float(x), float(y)) for x, y in m["corners"]]
                kind = str(m.get("kind", "detected"))
                if len(corners) != 4 or kind not in KINDS or \
                        not all(math.isfinite(c) for p in corners for c in p):
                    raise ValueError
                markers.append(CameraMarker(int(m["id"]), corners, kind))
            except (KeyError, TypeError, ValueError):
                raise FrameError(f"camera: markers[{i}]: expected id, 4 finite corners "
                                 f"and a kind in {', '.join(KINDS)}") from None
        focus = body.get("focus")
        focus = float(focus) if isinstance(focus, (int, float)) and \
            not isinstance(focus, bool) and math.isfinite(focus) else None
        return cls(w, h, pixels, fw, fh, markers, focus, body.get("frame"), body.get("t"))


@dataclass(frozen=True)
class Layout:
    """Where the image goes in a ``cols`` x ``rows`` pane: ``dw`` x ``dh`` display pixels
    (half-block pixels or braille dots, both about square) from display pixel ``ox``."""

    cols: int
    rows: int
    dw: int
    dh: int
    ox: int
    scale: float  # display pixels per full-frame pixel
    per_col: int  # display pixels per cell across (1 half block, 2 braille)
    per_row: int  # display pixels per cell down (2 half block, 4 braille)


def layout(full_width: int, full_height: int, cols: int, rows: int, braille: bool) -> Layout:
    """Fit the frame's aspect into the pane, centred across, from the top."""
    pc, pr = (2, 4) if braille else (1, 2)
    pw, ph = max(cols, 0) * pc, max(rows, 0) * pr
    scale = min(pw / full_width, ph / full_height) if full_width and full_height else 0.0
    dw, dh = min(pw, round(full_width * scale)), min(ph, round(full_height * scale))
    ox = (pw - dw) // 2
    ox -= ox % pc  # start on a cell boundary
    return Layout(cols, rows, dw, dh, ox, scale, pc, pr)


def display_size(full_width: int, full_height: int, cols: int, rows: int,
                 braille: bool = False) -> tuple[int, int]:
    """The thumbnail size (width, height) worth asking the daemon for, for this pane."""
    lay = layout(full_width, full_height, cols, rows, braille)
    return max(1, lay.dw), max(1, lay.dh)


def _sample(frame: CameraFrame, lay: Layout) -> list[list[int]]:
    """Grey levels of the ``dh`` x ``dw`` display pixels (box average of the thumbnail)."""
    sx, sy = frame.width / max(lay.dw, 1), frame.height / max(lay.dh, 1)
    px, w = frame.pixels, frame.width
    out = []
    for j in range(lay.dh):
        y0 = int(j * sy)
        y1 = max(y0 + 1, min(frame.height, int((j + 1) * sy)))
        row = []
        for i in range(lay.dw):
            x0 = int(i * sx)
            x1 = max(x0 + 1, min(w, int((i + 1) * sx)))
            if x1 - x0 == 1 and y1 - y0 == 1:
                row.append(px[y0 * w + x0])
            else:
                tot = 0
                for yy in range(y0, y1):
                    base = yy * w
                    tot += sum(px[base + x0:base + x1])
                row.append(tot // ((x1 - x0) * (y1 - y0)))
        out.append(row)
    return out


def _outline_pixels(m: CameraMarker, lay: Layout) -> list[tuple[int, int]]:
    """Display pixels along the marker's four edges (inside the image area)."""
    pts = [(lay.ox + x * lay.scale, y * lay.scale) for x, y in m.corners]
    out = []
    for k in range(4):
        (x0, y0), (x1, y1) = pts[k], pts[(k + 1) % 4]
        n = max(1, math.ceil(max(abs(x1 - x0), abs(y1 - y0))))
        dashed = m.kind == "expected"
        for s in range(n + 1):
            if dashed and s % 3 == 2:
                continue
            x, y = math.floor(x0 + (x1 - x0) * s / n), math.floor(y0 + (y1 - y0) * s / n)
            if lay.ox <= x < lay.ox + lay.dw and 0 <= y < lay.dh:
                out.append((x, y))
    return out


def marker_label(m: CameraMarker) -> str:
    return {"expected": f"({m.id})", "suspect": f"{m.id}?"}.get(m.kind, str(m.id))


_GREY_STYLES: dict[tuple[int, int], Style] = {}


def _grey(top: int, bottom: int) -> Style:
    # 64 levels: enough for a thumbnail, and few enough styles to cache.
    key = (top >> 2, bottom >> 2)
    s = _GREY_STYLES.get(key)
    if s is None:
        t, b = key[0] * 4 + 2, key[1] * 4 + 2
        s = Style(color=Color.from_rgb(t, t, t), bgcolor=Color.from_rgb(b, b, b))
        _GREY_STYLES[key] = s
    return s


# 4x4 Bayer matrix for ordered dithering of the braille dots.
_BAYER = ((0, 8, 2, 10), (12, 4, 14, 6), (3, 11, 1, 9), (15, 7, 13, 5))


def render_camera(frame: CameraFrame | None, cols: int, rows: int, braille: bool = False,
                  dim: bool = False) -> list[Text]:
    """``rows`` lines of ``cols`` cells showing ``frame`` (blank lines when None).

    Half blocks: each cell is two grey pixels (top as foreground, bottom as background).
    Braille: each cell is 2 x 4 dithered dots (works without colour). Outlines are drawn
    in their kind's colour; labels at the marker centres. ``dim``: stale data, drawn grey.
    """
    blank = [Text(" " * max(cols, 0), end="") for _ in range(max(rows, 0))]
    if frame is None or cols <= 0 or rows <= 0:
        return blank
    lay = layout(frame.full_width, frame.full_height, cols, rows, braille)
    if lay.dw <= 0 or lay.dh <= 0:
        return blank
    grey = _sample(frame, lay)
    ink: dict[tuple[int, int], str] = {}
    order = sorted(frame.markers, key=lambda m: KINDS.index(m.kind), reverse=True)
    for m in order:  # detected drawn last, over an expected outline that touches it
        for p in _outline_pixels(m, lay):
            ink[p] = "bright_black" if dim else KIND_COLOR[m.kind]
    if braille:
        lines = _braille_lines(grey, ink, lay, dim)
    else:
        lines = _block_lines(grey, ink, lay, dim)
    _labels(lines, frame.markers, lay, dim)
    return [_to_text(cells) for cells in lines]


Cell = tuple[str, Style | str | None]


def _block_lines(grey: list[list[int]], ink: dict[tuple[int, int], str], lay: Layout,
                 dim: bool) -> list[list[Cell]]:
    lines: list[list[Cell]] = []
    c0 = lay.ox
    for cy in range(lay.rows):
        cells: list[Cell] = [(" ", None)] * lay.cols
        y0, y1 = 2 * cy, 2 * cy + 1
        if y0 < lay.dh:
            for i in range(lay.dw):
                cx = c0 + i
                if cx >= lay.cols:
                    break
                top = grey[y0][i]
                bot = grey[y1][i] if y1 < lay.dh else 0
                if dim:
                    top, bot = top // 3, bot // 3
                it, ib = ink.get((cx, y0)), ink.get((cx, y1))
                if it is None and ib is None:
                    cells[cx] = (HALF_BLOCK, _grey(top, bot))
                else:
                    tc = it or Color.from_rgb(top, top, top)
                    bc = ib or Color.from_rgb(bot, bot, bot)
                    cells[cx] = (HALF_BLOCK, Style(color=tc, bgcolor=bc))
        lines.append(cells)
    return lines


def _braille_lines(grey: list[list[int]], ink: dict[tuple[int, int], str], lay: Layout,
                   dim: bool) -> list[list[Cell]]:
    canvas = BrailleCanvas(lay.cols, lay.rows)
    base = "bright_black" if dim else "white"
    for j, row in enumerate(grey):
        for i, g in enumerate(row):
            if g * 16 > (_BAYER[j % 4][i % 4] + 0.5) * 255:
                canvas.dot(lay.ox + i, j, base)
    for (x, y), style in ink.items():
        canvas.dot(x, y, style)
    return [[(ch, style) for text, style in run for ch in text] for run in canvas.runs()]


def _labels(lines: list[list[Cell]], markers: list[CameraMarker], lay: Layout,
            dim: bool) -> None:
    taken: set[tuple[int, int]] = set()
    for m in sorted(markers, key=lambda m: KINDS.index(m.kind)):  # detected first
        label = marker_label(m)
        cx_pix = lay.ox + sum(x for x, _ in m.corners) / 4 * lay.scale
        cy_pix = sum(y for _, y in m.corners) / 4 * lay.scale
        cx = int(cx_pix // lay.per_col) - len(label) // 2
        cy = int(cy_pix // lay.per_row)
        cx = min(max(cx, 0), lay.cols - len(label))
        span = {(cx + k, cy) for k in range(len(label))}
        if not 0 <= cy < lay.rows or cx < 0 or span & taken:
            continue
        taken |= span
        style = "bold black on bright_black" if dim else f"bold black on {KIND_COLOR[m.kind]}"
        for k, ch in enumerate(label):
            lines[cy][cx + k] = (ch, style)


def _to_text(cells: list[Cell]) -> Text:
    out = Text(no_wrap=True, overflow="crop", end="")
    run: list[str] = []
    style: Style | str | None = None
    for ch, st in cells:
        if st is not style and run:
            out.append("".join(run), style or "")
            run = []
        style = st
        run.append(ch)
    if run:
        out.append("".join(run), style or "")
    return out


def camera_caption(frame: CameraFrame | None, best_focus: float | None = None) -> str:
    """One line under the image: counts by kind and the focus figure (with the best seen)."""
    if frame is None:
        return "no camera image yet"
    n = {k: sum(m.kind == k for m in frame.markers) for k in KINDS}
    parts = [f"{n['detected'] + n['suspect'] + n['rejected']} seen"]
    if n["suspect"]:
        parts.append(f"{n['suspect']} suspect (?)")
    if n["rejected"]:
        parts.append(f"{n['rejected']} rejected")
    # Named as the image labels them: "(13)" beside a dashed outline.
    unseen = [f"({m.id})" for m in frame.markers if m.kind == "expected"]
    shown = " ".join(unseen[:2]) + (" …" if len(unseen) > 2 else "")
    parts.append(f"{n['expected']} expected unseen" + (f" {shown}" if unseen else ""))
    if frame.focus is not None:
        f = f"focus {frame.focus:.0f}"
        if best_focus is not None and best_focus > 0:
            f += f" (best {best_focus:.0f})"
        parts.append(f)
    else:
        parts.append("focus -")
    return " · ".join(parts)


class CameraView(Widget):
    """Shows the latest :class:`CameraFrame` scaled to the widget; ``braille`` toggles the
    drawing; ``dim`` greys it (stale or stopped daemon)."""

    DEFAULT_CSS = "CameraView { height: 1fr; width: 1fr; }"

    def __init__(self, id: str | None = None) -> None:
        super().__init__(id=id)
        self.frame: CameraFrame | None = None
        self.braille = False
        self.dim = False
        self.best_focus: float | None = None
        self._strips: list[Strip] | None = None
        self._strip_size: tuple[int, int] | None = None

    def set_frame(self, frame: CameraFrame | None) -> None:
        self.frame = frame
        if frame is not None and frame.focus is not None:
            self.best_focus = max(self.best_focus or 0.0, frame.focus)
        self._strips = None
        self.refresh()

    def set_dim(self, dim: bool) -> None:
        if dim != self.dim:
            self.dim = dim
            self._strips = None
            self.refresh()

    def toggle_braille(self) -> None:
        self.braille = not self.braille
        self._strips = None
        self.refresh()

    def reset_focus(self) -> None:
        self.best_focus = None

    def render_line(self, y: int) -> Strip:
        w, h = self.size.width, self.size.height
        if self._strips is None or self._strip_size != (w, h):
            self._strip_size = (w, h)
            texts = render_camera(self.frame, w, h, self.braille, self.dim)
            self._strips = [Strip(list(t.render(self.app.console)), w) for t in texts]
        if 0 <= y < len(self._strips):
            return self._strips[y]
        return Strip([Segment(" " * w)], w)


class CameraPane(Vertical):
    """The Camera tab: caption, the image, the keys. The app renews the daemon's
    ``camera_watch`` lease while this tab is shown (thumbnails cost nothing otherwise)."""

    # Short labels: at 80 columns the footer must still show ^q Quit.
    BINDINGS = [Binding("s", "snapshot(False)", "PNG"),
                Binding("o", "snapshot(True)", "PNG+overlay"),
                Binding("b", "braille", "Braille"),
                Binding("f", "reset_focus", "Best focus")]

    def compose(self) -> ComposeResult:
        yield Static("camera: waiting for the first image…", id="camera-caption",
                     classes="summary", markup=False)
        yield CameraView(id="camera-view")

    def on_mount(self) -> None:
        self.query_one(CameraView).can_focus = True

    @property
    def view(self) -> CameraView:
        return self.query_one(CameraView)

    def show_frame(self, frame: CameraFrame) -> None:
        self.view.set_frame(frame)
        self.show_caption(camera_caption(frame, self.view.best_focus))

    def show_caption(self, text: str, error: bool = False) -> None:
        self.query_one("#camera-caption", Static).update(
            Text(text, style="bold red" if error else ""), layout=False)

    def set_dim(self, dim: bool) -> None:
        self.view.set_dim(dim)

    def action_snapshot(self, overlay: bool) -> None:
        self.post_message(ControlRequest("snapshot", {"overlay": overlay}))

    def action_braille(self) -> None:
        self.view.toggle_braille()

    def action_reset_focus(self) -> None:
        self.view.reset_focus()
        if self.view.frame is not None:
            self.show_caption(camera_caption(self.view.frame, self.view.best_focus))
