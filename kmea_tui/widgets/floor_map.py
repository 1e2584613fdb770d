"""Top view of the floor to scale in braille: outline, markers by id, robots, error vectors."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from rich.segment import Segment
from rich.style import Style
from rich.text import Text
from textual.geometry import Region
from textual.strip import Strip
from textual.widget import Widget

from kmea_tui.canvas import BrailleCanvas, Viewport, heading_arrow, nice_magnification

# Styles use the 16 ANSI colours only, so they read the same on any terminal.
STYLE_OUTLINE = "bright_black"
STYLE_DETECTED = "bold green"
STYLE_UNSEEN = "bright_black"
STYLE_MOVED = "bold red"
STYLE_FOREIGN = "bold cyan"
# Suspect markers (corners hidden or at the image border: not references this frame) stand
# out from the yellow error vectors by their background.
STYLE_SUSPECT = "bold black on yellow"
STYLE_VECTOR = "yellow"
STYLE_ROBOT = "bold magenta"
STYLE_STALE = "magenta"
STYLE_AXES = "blue"

# Margin around the markers' extent, metres.
EXTENT_MARGIN = 0.155
# Auto magnification makes the longest error vector about this fraction of the floor's width.
VECTOR_FRACTION = 0.08
ROBOT_HEADING_M = 0.12


@dataclass
class MapData:
    """What the map shows; marker and robot dicts are the telemetry's."""

    markers: list[dict[str, Any]] = field(default_factory=list)
    robots: list[dict[str, Any]] = field(default_factory=list)
    moved: set[int] = field(default_factory=set)


def _num(v: Any) -> float | None:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None


def marker_error_vector(m: dict[str, Any]) -> tuple[float, float] | None:
    """(dx, dy) m from the map position to the estimated one, or None if unknown or the
    marker is suspect (its estimate is not trustworthy: no vector rather than a false one)."""
    x, y, mx, my = (_num(m.get(k)) for k in ("x", "y", "map_x", "map_y"))
    if None in (x, y, mx, my) or not m.get("detected", x is not None) or m.get("suspect"):
        return None
    return x - mx, y - my  # type: ignore[operator]


class FloorMap(Widget):
    """Draws :class:`MapData` to fill the widget; ``magnification`` None = automatic."""

    DEFAULT_CSS = "FloorMap { height: 1fr; width: 1fr; }"

    def __init__(self, id: str | None = None) -> None:
        super().__init__(id=id)
        self.data = MapData()
        # The daemon's map extent (status ``map.extent``: xmin, xmax, ymin, ymax, m): the
        # outline before any marker estimate, and all of it on a fusion node.
        self.outline: tuple[float, ...] | None = None
        # Grows to every robot position seen outside the outline, so no robot is drawn off
        # the floor (and the outline does not follow a moving robot back and forth; robots
        # on the floor never change it, whichever telemetry the UI happened to draw).
        self._robots_extent: tuple[float, float, float, float] | None = None
        self.magnification: float | None = None
        self._auto_mag = 100.0
        self._strips: list[Strip] | None = None
        # The last lines drawn by row key (BrailleCanvas.row_keys), with the (style, width)
        # they were drawn for.
        self._row_cache: tuple[tuple[Style, int], dict[tuple, Strip]] | None = None

    def set_data(self, data: MapData) -> None:
        """Show ``data``, repainting only the lines that differ from what is shown (robots
        move a few lines a frame; the floor stays put)."""
        self.data = data
        x0, x1, y0, y1 = self.extent()
        for r in data.robots:
            x, y = _num(r.get("x")), _num(r.get("y"))
            if x is None or y is None or (x0 <= x <= x1 and y0 <= y <= y1):
                continue  # drawn already: the outline stays as the map and markers make it
            e = self._robots_extent or (x, x, y, y)
            self._robots_extent = (min(e[0], x), max(e[1], x), min(e[2], y), max(e[3], y))
        self._update_auto_magnification()
        old = self._strips
        if old is None or len(old) != self.size.height or not self.is_mounted:
            self.refresh()
            return
        new = self._strips = self._render_strips()
        width = self.size.width
        changed = [y for y, (a, b) in enumerate(zip(old, new, strict=True)) if a is not b]
        start = 0
        for i, y in enumerate(changed):
            if i + 1 == len(changed) or changed[i + 1] != y + 1:
                super().refresh(Region(0, changed[start], width, y - changed[start] + 1))
                start = i + 1

    @property
    def effective_magnification(self) -> float:
        return self.magnification if self.magnification is not None else self._auto_mag

    def _update_auto_magnification(self) -> None:
        # Scaled to the markers that are not moved: a moved marker's long vector
        # is clipped at the edge instead of shrinking every other vector to nothing.
        errs = [math.hypot(*v) for m in self.data.markers
                if m.get("id") not in self.data.moved
                and (v := marker_error_vector(m)) is not None]
        x0, x1, y0, y1 = self.extent()
        suggested = nice_magnification(max(errs, default=0.0),
                                       VECTOR_FRACTION * max(x1 - x0, y1 - y0))
        # Hysteresis: only change by more than one 1-2-5 step, so the map doesn't flicker.
        ratio = suggested / self._auto_mag
        if ratio > 2.6 or ratio < 1 / 2.6 or not errs:
            self._auto_mag = suggested

    def extent(self) -> tuple[float, float, float, float]:
        """The world rectangle drawn as the outline (m): the markers' extent (else the
        map's, from the status) and every robot position seen outside it, plus a margin."""
        xs, ys = [], []
        for e in (self.outline, self._robots_extent):
            if e is not None and len(e) == 4:
                xs += [e[0], e[1]]
                ys += [e[2], e[3]]
        for m in self.data.markers:
            for kx, ky in (("map_x", "map_y"), ("x", "y")):
                x, y = _num(m.get(kx)), _num(m.get(ky))
                if x is not None and y is not None:
                    xs.append(x)
                    ys.append(y)
                    break
        if not xs:
            return (-0.85, 0.85, -0.6, 0.6)
        return (min(xs) - EXTENT_MARGIN, max(xs) + EXTENT_MARGIN,
                min(ys) - EXTENT_MARGIN, max(ys) + EXTENT_MARGIN)

    def metres_per_cell(self) -> float:
        c = BrailleCanvas(self.size.width, self.size.height)
        x0, x1, y0, y1 = self.extent()
        return 2.0 / Viewport(x0, x1, y0, y1, c.width, c.height).scale

    # Line API with strips cached until the data or the size changes: the map is thousands
    # of cells and is redrawn only when a new batch of telemetry arrives.
    def refresh(self, *args: Any, **kwargs: Any) -> FloorMap:
        self._strips = None
        return super().refresh(*args, **kwargs)

    def on_resize(self) -> None:
        self._strips = None

    def _render_strips(self) -> list[Strip]:
        """The map's lines; a line that draws as before is the same Strip object as before
        (only rows whose dots, styles or text changed are built again)."""
        width, height = self.size.width, self.size.height
        canvas = BrailleCanvas(width, height)
        if canvas.cols >= 4 and canvas.rows >= 2:
            self.draw(canvas)
        base = self.rich_style
        cache: dict[str | Style | None, Style] = {}

        def style_of(s: str | Style | None) -> Style:
            if s not in cache:
                cache[s] = base + (Style.parse(s) if isinstance(s, str) else (s or Style()))
            return cache[s]

        keys = canvas.row_keys()
        old: dict[tuple, Strip] = {}
        if self._row_cache is not None and self._row_cache[0] == (base, width):
            old = self._row_cache[1]
        strips = [old.get(key) or Strip([Segment(text, style_of(st))
                                         for text, st in canvas.row_runs(cy)], width)
                  for cy, key in enumerate(keys)]
        self._row_cache = ((base, width), dict(zip(keys, strips, strict=True)))
        return strips or [Strip.blank(width, base)]

    def render_line(self, y: int) -> Strip:
        if self._strips is None or len(self._strips) != self.size.height:
            self._strips = self._render_strips()
        if 0 <= y < len(self._strips):
            return self._strips[y]
        return Strip.blank(self.size.width, self.rich_style)

    def draw(self, canvas: BrailleCanvas) -> None:
        x0, x1, y0, y1 = self.extent()
        vp = Viewport(x0, x1, y0, y1, canvas.width, canvas.height)
        canvas.rect(*vp.to_dots(x0, y0), *vp.to_dots(x1, y1), STYLE_OUTLINE)
        # Origin axes, 10 cm each, so the frame's orientation is visible.
        if x0 <= 0 <= x1 and y0 <= 0 <= y1:
            canvas.line(*vp.to_dots(0, 0), *vp.to_dots(0.1, 0), STYLE_AXES)
            canvas.line(*vp.to_dots(0, 0), *vp.to_dots(0, 0.1), STYLE_AXES)
        mag = self.effective_magnification
        markers = self.data.markers
        for m in markers:
            v = marker_error_vector(m)
            if v is None:
                continue
            mx, my = float(m["map_x"]), float(m["map_y"])
            style = STYLE_MOVED if m.get("id") in self.data.moved else STYLE_VECTOR
            canvas.line(*vp.to_dots(mx, my), *vp.to_dots(mx + mag * v[0], my + mag * v[1]),
                        style)
        for r in self.data.robots:
            x, y, th = _num(r.get("x")), _num(r.get("y")), _num(r.get("theta"))
            if x is None or y is None or th is None:
                continue
            style = STYLE_STALE if r.get("stale") else STYLE_ROBOT
            hx, hy = x + ROBOT_HEADING_M * math.cos(th), y + ROBOT_HEADING_M * math.sin(th)
            canvas.line(*vp.to_dots(x, y), *vp.to_dots(hx, hy), style)

        # Robots first: their arrow and name stand for their markers.
        on_robots: set[int] = set()
        for r in self.data.robots:
            on_robots.update(i for i in (r.get("markers") or []) if isinstance(i, int))

        def rank(m: dict[str, Any]) -> int:
            # Labels are placed in this order; a later one that would touch an earlier one
            # becomes a dot. Moved first, then seen floor markers, then the rest.
            if m.get("id") in self.data.moved:
                return 0
            floor = abs(_num(m.get("map_z")) or 0.0) < 1e-6
            return (1 if floor else 2) if m.get("detected") else (3 if floor else 4)

        def place(m: dict[str, Any]) -> None:
            in_map = _num(m.get("map_x")) is not None and _num(m.get("map_y")) is not None
            if in_map:
                px, py = float(m["map_x"]), float(m["map_y"])
            elif _num(m.get("x")) is not None and _num(m.get("y")) is not None:
                px, py = float(m["x"]), float(m["y"])
            else:
                return
            if not in_map:
                style = STYLE_FOREIGN
            elif m.get("id") in self.data.moved:
                style = STYLE_MOVED
            elif m.get("detected") and m.get("suspect"):
                style = STYLE_SUSPECT
            elif m.get("detected"):
                style = STYLE_DETECTED
            else:
                style = STYLE_UNSEEN
            label = str(m.get("id"))
            cx, cy = vp.to_cell(px, py)
            lx = cx - (len(label) - 1) // 2
            # One free cell either side keeps neighbouring ids apart ("11 56", not "1156").
            if canvas.free(lx - 1, cy, len(label) + 2):
                canvas.text(lx, cy, label, style)
            else:
                canvas.dot(*vp.to_dots(px, py), style)

        # Suspect markers are usually partly under a robot: their labels go before the
        # robots' names, which would hide them, then the rest.
        ordered = [m for m in sorted(markers, key=rank) if m.get("id") not in on_robots]
        first = [m for m in ordered if m.get("detected") and m.get("suspect")]
        for m in first:
            place(m)
        self._draw_robots(canvas, vp)
        for m in ordered:
            if not (m.get("detected") and m.get("suspect")):
                place(m)

    def _draw_robots(self, canvas: BrailleCanvas, vp: Viewport) -> None:
        for r in self.data.robots:
            x, y, th = _num(r.get("x")), _num(r.get("y")), _num(r.get("theta"))
            if x is None or y is None or th is None:
                continue
            style = STYLE_STALE if r.get("stale") else STYLE_ROBOT
            cx, cy = vp.to_cell(x, y)
            canvas.text(cx, cy, heading_arrow(th), style)
            name = str(r.get("name", ""))
            # The name goes behind the robot (not over its heading line), else below/above.
            right, left = (cx + 1, cy), (cx - len(name), cy)
            sides = (left, right) if math.cos(th) >= 0 else (right, left)
            for nx, ny in (*sides, (cx, cy + 1), (cx, cy - 1)):
                if canvas.free(nx, ny, len(name)):
                    canvas.text(nx, ny, name, style)
                    break


class MapPane(Widget):
    """The floor map with its legend; ``+``/``-`` change the error magnification, ``a`` auto."""

    DEFAULT_CSS = """
    MapPane { layout: vertical; }
    MapPane > #map-legend { height: auto; }
    """

    def compose(self):  # type: ignore[no-untyped-def]
        from textual.widgets import Static

        yield FloorMap(id="floor-map")
        yield Static("", id="map-legend")

    def on_mount(self) -> None:
        self.query_one(FloorMap).can_focus = True

    def set_data(self, data: MapData) -> None:
        fm = self.query_one(FloorMap)
        fm.set_data(data)
        self.update_legend()

    def update_legend(self) -> None:
        from textual.widgets import Static

        from kmea_tui.widgets.live_table import show_line

        fm = self.query_one(FloorMap)
        mag = fm.effective_magnification
        auto = "auto" if fm.magnification is None else "fixed"
        cell = fm.metres_per_cell() * 100 if fm.size.width else float("nan")
        show_line(self.query_one("#map-legend", Static), Text.assemble(
            ("■", STYLE_DETECTED), " seen ", ("■", STYLE_UNSEEN), " unseen ",
            ("■", STYLE_MOVED), " moved ", ("■", STYLE_SUSPECT), " suspect ",
            ("■", STYLE_FOREIGN), " not in map ",
            ("→", STYLE_ROBOT), " robot  ", ("⠤", STYLE_VECTOR),
            f" error ×{mag:g} ({auto}, +/-/a) · □ map extent · cell {cell:.1f} cm"))

    def on_resize(self) -> None:
        self.update_legend()

    def change_magnification(self, step: int) -> None:
        fm = self.query_one(FloorMap)
        series = [m * 10.0 ** e for e in range(0, 5) for m in (1, 2, 5)]
        cur = fm.effective_magnification
        i = min(range(len(series)), key=lambda k: abs(series[k] - cur))
        fm.magnification = series[max(0, min(len(series) - 1, i + step))]
        fm.refresh()
        self.update_legend()

    def auto_magnification(self) -> None:
        fm = self.query_one(FloorMap)
        fm.magnification = None
        fm._update_auto_magnification()
        fm.refresh()
        self.update_legend()
