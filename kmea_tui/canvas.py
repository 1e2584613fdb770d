"""Text drawing to scale: a braille dot canvas and the world-to-dot viewport.

A terminal cell is about twice as tall as wide, and a braille character holds 2 x 4 dots,
so dots are square and one scale serves both axes. Dot coordinates: x right, y down,
(0, 0) the top-left dot. World coordinates: metres, x right, y up (the floor frame).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from rich.style import Style
from rich.text import Text

# Bit of each dot in a braille cell, indexed [row][column] (Unicode braille patterns).
_BRAILLE_BITS = ((0x01, 0x08), (0x02, 0x10), (0x04, 0x20), (0x40, 0x80))
_BRAILLE_BASE = 0x2800
# The character of each dot pattern (none set: a blank).
_CHARS = [" "] + [chr(_BRAILLE_BASE + b) for b in range(1, 256)]


class BrailleCanvas:
    """``cols`` x ``rows`` cells = ``2 cols`` x ``4 rows`` dots, with text overlaid.

    Each cell has one style (the last dot drawn in it wins); text put in a cell replaces
    its dots.
    """

    def __init__(self, cols: int, rows: int) -> None:
        self.cols = max(0, cols)
        self.rows = max(0, rows)
        self._bits = [[0] * self.cols for _ in range(self.rows)]
        self._style: list[list[Style | str | None]] = [[None] * self.cols
                                                       for _ in range(self.rows)]
        self._text: dict[tuple[int, int], tuple[str, Style | str | None]] = {}

    @property
    def width(self) -> int:
        """Width in dots."""
        return 2 * self.cols

    @property
    def height(self) -> int:
        """Height in dots."""
        return 4 * self.rows

    def dot(self, x: float, y: float, style: Style | str | None = None) -> None:
        """Set the dot nearest (x, y) (dot units); outside the canvas is ignored."""
        ix, iy = math.floor(x), math.floor(y)
        if 0 <= ix < self.width and 0 <= iy < self.height:
            cx, cy = ix // 2, iy // 4
            self._bits[cy][cx] |= _BRAILLE_BITS[iy % 4][ix % 2]
            if style is not None:
                self._style[cy][cx] = style

    def is_set(self, x: int, y: int) -> bool:
        if not (0 <= x < self.width and 0 <= y < self.height):
            return False
        return bool(self._bits[y // 4][x // 2] & _BRAILLE_BITS[y % 4][x % 2])

    def line(self, x0: float, y0: float, x1: float, y1: float,
             style: Style | str | None = None) -> None:
        """Dots along the segment, one per dot step of the longer axis."""
        n = max(1, math.ceil(max(abs(x1 - x0), abs(y1 - y0))))
        for i in range(n + 1):
            t = i / n
            self.dot(x0 + (x1 - x0) * t, y0 + (y1 - y0) * t, style)

    def rect(self, x0: float, y0: float, x1: float, y1: float,
             style: Style | str | None = None) -> None:
        self.line(x0, y0, x1, y0, style)
        self.line(x1, y0, x1, y1, style)
        self.line(x1, y1, x0, y1, style)
        self.line(x0, y1, x0, y0, style)

    def text(self, cx: int, cy: int, s: str, style: Style | str | None = None) -> None:
        """Write ``s`` from cell (cx, cy) rightwards, clipped to the canvas."""
        for i, ch in enumerate(s):
            x = cx + i
            if 0 <= x < self.cols and 0 <= cy < self.rows:
                self._text[(x, cy)] = (ch, style)

    def free(self, cx: int, cy: int, n: int) -> bool:
        """No text yet in the ``n`` cells from (cx, cy), all inside the canvas."""
        return (cx >= 0 and cx + n <= self.cols and 0 <= cy < self.rows
                and all((cx + i, cy) not in self._text for i in range(n)))

    def runs(self) -> list[list[tuple[str, Style | str | None]]]:
        """Per row, the (text, style) runs of cells that share a style."""
        texts = self._texts_by_row()
        return [self.row_runs(cy, texts.get(cy, {})) for cy in range(self.rows)]

    def _texts_by_row(self) -> dict[int, dict[int, tuple[str, Style | str | None]]]:
        rows: dict[int, dict[int, tuple[str, Style | str | None]]] = {}
        for (cx, cy), v in self._text.items():
            rows.setdefault(cy, {})[cx] = v
        return rows

    def row_keys(self) -> list[tuple]:
        """Per row, a value equal for two canvases exactly when the row draws the same
        (a redraw can keep the lines whose key did not change)."""
        texts = self._texts_by_row()
        return [(tuple(self._bits[cy]), tuple(self._style[cy]),
                 tuple(sorted(texts[cy].items())) if cy in texts else ())
                for cy in range(self.rows)]

    def row_runs(self, cy: int, texts: dict[int, tuple[str, Style | str | None]] | None = None
                 ) -> list[tuple[str, Style | str | None]]:
        """Row ``cy``'s (text, style) runs; ``texts``: its text cells by column, if known."""
        if texts is None:
            texts = self._texts_by_row().get(cy, {})
        bits_row, style_row = self._bits[cy], self._style[cy]
        chars = [_CHARS[b] for b in bits_row]
        styles = [st if b else None for b, st in zip(bits_row, style_row, strict=True)]
        for cx, (ch, st) in texts.items():
            chars[cx], styles[cx] = ch, st
        row: list[tuple[str, Style | str | None]] = []
        start = 0
        for cx in range(1, self.cols + 1):
            if cx == self.cols or styles[cx] != styles[start]:
                row.append(("".join(chars[start:cx]), styles[start]))
                start = cx
        return row

    def render(self) -> Text:
        """The canvas as Rich text (rows joined by newlines)."""
        out = Text(no_wrap=True, overflow="crop", end="")
        for cy, row in enumerate(self.runs()):
            if cy:
                out.append("\n")
            for text, style in row:
                out.append(text, style or "")
        return out


@dataclass(frozen=True)
class Viewport:
    """Maps the world rectangle ``[x0, x1] x [y0, y1]`` (m) into a dot canvas, to scale.

    ``scale`` is dots per metre (the same on both axes); the rectangle is centred.
    """

    x0: float
    x1: float
    y0: float
    y1: float
    width: int
    height: int

    @property
    def scale(self) -> float:
        w = max(self.x1 - self.x0, 1e-9)
        h = max(self.y1 - self.y0, 1e-9)
        return max(min((self.width - 1) / w, (self.height - 1) / h), 1e-9)

    def to_dots(self, x: float, y: float) -> tuple[float, float]:
        s = self.scale
        ox = (self.width - 1 - s * (self.x1 - self.x0)) / 2
        oy = (self.height - 1 - s * (self.y1 - self.y0)) / 2
        return ox + (x - self.x0) * s, oy + (self.y1 - y) * s

    def to_cell(self, x: float, y: float) -> tuple[int, int]:
        dx, dy = self.to_dots(x, y)
        return math.floor(dx) // 2, math.floor(dy) // 4


def nice_magnification(max_error: float, target: float) -> float:
    """Magnification from the 1-2-5 series making ``max_error`` (m) about ``target`` m long.

    Rounded down so the longest vector never exceeds the target; 1 to 10000.
    """
    if not (max_error > 0 and math.isfinite(max_error)):
        return 100.0
    raw = target / max_error
    if raw <= 1:
        return 1.0
    exp = math.floor(math.log10(raw))
    best = 1.0
    for e in (exp - 1, exp):
        for m in (1, 2, 5):
            v = m * 10.0 ** e
            if v <= raw * (1 + 1e-9):
                best = max(best, v)
    return min(best, 10000.0)


ARROWS = "→↗↑↖←↙↓↘"


def heading_arrow(theta: float) -> str:
    """The arrow of the 8 compass directions nearest ``theta`` (rad, CCW from +x)."""
    return ARROWS[round(theta / (math.pi / 4)) % 8]
