"""A live table on Textual's Line API: rows keyed, updated in place, only changed lines redrawn.

Textual's ``DataTable`` redraws every visible line when any one cell changes (its caches are
keyed on a table-wide update counter): at 4 repaints a second a 40-row markers table took a
tenth of a core. :class:`LiveTable` keeps one rendered strip per row, rebuilt only when that
row's cells (or the column widths, the cursor or the styles) change, and asks Textual to
repaint only the screen lines whose row changed (``refresh(Region)``). A row that moves
(sorting, rows coming or going) repaints the lines it left and the lines it reached.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

from rich.cells import cell_len, set_cell_size
from rich.segment import Segment
from rich.style import Style
from rich.text import Text
from textual import events
from textual.binding import Binding, BindingType
from textual.geometry import Region, Size
from textual.message import Message
from textual.scroll_view import ScrollView
from textual.strip import Strip

DASH = "-"
# Blank columns either side of a cell's text (DataTable's default ``cell_padding``).
PAD = 1

Cell = str | Text


def fmt(value: Any, spec: str = ".3f", scale: float = 1.0) -> str:
    """``value * scale`` formatted with ``spec``; a dash for missing values."""
    if value is None or isinstance(value, bool):
        return DASH if value is None else ("yes" if value else "no")
    try:
        text = format(float(value) * scale, spec)
    except (TypeError, ValueError):
        return str(value)
    # "-0.000" says nothing more than "0.000" and makes columns flicker.
    if text.startswith("-") and not text.strip("-0."):
        text = text[1:]
    return text


def show_line(widget: Any, text: Text) -> None:
    """``widget.update(text)`` for a one- or two-line summary, without the screen-wide
    layout pass ``Static.update`` asks for unless the number of wrapped lines changes
    (at 4 repaints a second the layout passes were most of the UI's time)."""
    if text == getattr(widget, "_shown_text", None):
        return
    width = max(1, widget.content_size.width or widget.size.width or 80)
    lines = -(-text.cell_len // width)
    widget.update(text, layout=lines != getattr(widget, "_shown_lines", None))
    widget._shown_text, widget._shown_lines = text, lines


def _value_key(value: Any) -> Any:
    """A hashable stand-in for a cell value (rich ``Text`` is mutable: its text and
    styles)."""
    if isinstance(value, Text):
        return ("T", value.plain, str(value.style), value.justify,
                tuple((sp.start, sp.end, str(sp.style)) for sp in value.spans))
    return value


@dataclass(eq=False)
class LiveRow:
    """One row: its key, raw values (for sorting) and cells in column order. The object
    stays the same while the row is updated in place."""

    key: str
    raw: dict[str, Any]
    cells: tuple[Cell, ...]
    # The cells as compared (a rich Text equals another with the same text in another
    # colour): the row is drawn again when this changes.
    sig: tuple
    version: int = 0
    # The row's rendered line and what it was rendered with (see LiveTable._row_strip).
    strip: Strip | None = field(default=None, repr=False)
    strip_key: tuple | None = field(default=None, repr=False)


class LiveTable(ScrollView, can_focus=True):
    """Rows keyed by a string; :meth:`sync` adds, updates and removes rows.

    Columns are ``(key, label)`` pairs. Sorting: ``s`` cycles the sort column, ``S`` reverses
    it, a click on a header sorts by that column (again: reverses); the sort value of a row
    comes from ``sort_value(raw_row, column_key)``. A row cursor moves with the arrows,
    page keys and clicks. Column widths fit the widest cell seen and never shrink (a
    column that narrows and widens again would make the whole table jump).
    """

    DEFAULT_CSS = """
    LiveTable {
        background: $surface;
        color: $foreground;
        &:focus {
            background-tint: $foreground 5%;
            & > .live-table--cursor {
                background: $block-cursor-background;
                color: $block-cursor-foreground;
                text-style: $block-cursor-text-style;
            }
            & > .live-table--header { background-tint: $foreground 5%; }
        }
        & > .live-table--header { text-style: bold; background: $panel; color: $foreground; }
        &:ansi > .live-table--header { background: ansi_bright_blue; color: ansi_default; }
        & > .live-table--cursor {
            background: $block-cursor-blurred-background;
            color: $block-cursor-blurred-foreground;
            text-style: $block-cursor-blurred-text-style;
        }
    }
    """
    COMPONENT_CLASSES: ClassVar[set[str]] = {"live-table--header", "live-table--cursor"}

    BINDINGS: ClassVar[list[BindingType]] = [
        Binding("s", "cycle_sort", "Sort col"),
        Binding("S", "reverse_sort", "Reverse", show=False),
        Binding("up", "cursor_up", "Cursor up", show=False),
        Binding("down", "cursor_down", "Cursor down", show=False),
        Binding("pageup", "page_up", "Page up", show=False),
        Binding("pagedown", "page_down", "Page down", show=False),
        Binding("home,ctrl+home", "cursor_home", "Top", show=False),
        Binding("end,ctrl+end", "cursor_end", "Bottom", show=False),
        Binding("left", "scroll_left", "Scroll left", show=False),
        Binding("right", "scroll_right", "Scroll right", show=False),
    ]

    def __init__(self, columns: Sequence[tuple[str, str]], *,
                 sort_value: Callable[[dict[str, Any], str], Any] | None = None,
                 sort_column: str | None = None, id: str | None = None) -> None:
        super().__init__(id=id)
        self._columns = list(columns)
        self._sort_value = sort_value
        self.sort_column = sort_column or self._columns[0][0]
        self.sort_reverse = False
        self.rows: dict[str, LiveRow] = {}
        self.raw: dict[str, dict[str, Any]] = {}
        self._order: list[str] = []  # row keys in display order
        self._widths = [cell_len(label) for _, label in self._columns]
        self.cursor_row = 0
        self._cell_cache: dict[tuple, list[Segment]] = {}
        self._header: tuple[tuple, Strip] | None = None
        # Counters the tests read to prove rows are updated in place, not rebuilt, and that
        # only what changed is drawn again.
        self.rows_added = 0
        self.rows_removed = 0
        self.cells_updated = 0
        self.lines_rendered = 0

    # -- the data --------------------------------------------------------------------------
    @property
    def column_keys(self) -> list[str]:
        return [k for k, _ in self._columns]

    @property
    def row_count(self) -> int:
        return len(self._order)

    def get_cell(self, row_key: str, column_key: str) -> Cell:
        """The cell shown in row ``row_key``, column ``column_key`` (KeyError if none)."""
        return self.rows[str(row_key)].cells[self.column_keys.index(column_key)]

    def get_row_at(self, index: int) -> list[Cell]:
        """The cells of the row shown at ``index`` (0 = the first row under the header)."""
        return list(self.rows[self._order[index]].cells)

    def row_key_at(self, index: int) -> str:
        return self._order[index]

    def sync(self, rows: dict[str, tuple[dict[str, Any], Sequence[Cell]]]) -> None:
        """Make the table show exactly ``rows``: {key: (raw values, cells in column order)}.

        Only rows whose cells changed are rendered and repainted; the rows are sorted again
        only when a row came or went or a sort value changed.
        """
        before = self._line_signatures()
        resort = False
        widths = list(self._widths)
        for key, (raw, cells) in rows.items():
            cells = tuple(cells)
            row = self.rows.get(key)
            self.raw[key] = raw
            if row is None:
                row = self.rows[key] = LiveRow(key, raw, cells, tuple(map(_value_key, cells)))
                self._order.append(key)
                self.rows_added += 1
                resort = True
            else:
                old_raw, row.raw = row.raw, raw
                sig = tuple(map(_value_key, cells))
                if sig == row.sig:
                    continue  # nothing to draw; its sort value cannot have changed either
                self.cells_updated += sum(1 for a, b in zip(row.sig, sig, strict=True)
                                          if a != b)
                row.cells, row.sig = cells, sig
                row.version += 1
                if self._sort_of(old_raw) != self._sort_of(raw):
                    resort = True
            for i, cell in enumerate(cells):
                if (n := cell.cell_len if isinstance(cell, Text) else cell_len(cell)) > widths[i]:
                    widths[i] = n
        gone = [k for k in self._order if k not in rows]
        for key in gone:
            del self.rows[key]
            self.raw.pop(key, None)
            self.rows_removed += 1
        if gone:
            self._order = [k for k in self._order if k in self.rows]
        if resort:
            self._sort_rows()
        self._after_change(before, widths)

    def clear(self) -> None:
        """Remove every row."""
        before = self._line_signatures()
        self.rows_removed += len(self._order)
        self.rows.clear()
        self.raw.clear()
        self._order.clear()
        self._after_change(before, self._widths)

    # -- sorting ---------------------------------------------------------------------------
    def _sort_of(self, raw: dict[str, Any]) -> Any:
        col = self.sort_column
        return self._sort_value(raw, col) if self._sort_value else raw.get(col)

    def _sort_rows(self) -> None:
        def value(key: str) -> Any:
            v = self._sort_of(self.rows[key].raw)
            # Missing values sort last whatever the direction.
            missing = v is None
            if self.sort_reverse:
                missing = not missing
            return (missing, v if v is not None else 0)

        self._order.sort(key=value, reverse=self.sort_reverse)

    def apply_sort(self) -> None:
        before = self._line_signatures()
        self._sort_rows()
        self._after_change(before, self._widths)

    def _set_sort(self, column: str, reverse: bool) -> None:
        self.sort_column, self.sort_reverse = column, reverse
        self.apply_sort()
        if self.is_mounted:
            self.refresh(Region(0, 0, max(self.size.width, self.virtual_size.width), 1))
        self.post_message(self.SortChanged(self))

    def action_cycle_sort(self) -> None:
        keys = self.column_keys
        self._set_sort(keys[(keys.index(self.sort_column) + 1) % len(keys)], self.sort_reverse)

    def action_reverse_sort(self) -> None:
        self._set_sort(self.sort_column, not self.sort_reverse)

    def sort_label(self) -> str:
        label = dict(self._columns).get(self.sort_column, self.sort_column)
        return f"sort {label}{self._arrow()}"

    def _arrow(self) -> str:
        return "▼" if self.sort_reverse else "▲"

    def header_label(self, key: str, label: str, width: int) -> str:
        """A column's title in its header cell of ``width`` columns: the sort column's
        ends in its arrow. Columns are as wide as their widest cell, often exactly their
        title: the title loses its last letters rather than the arrow, which is what
        a narrow (80x24) table must still show; widening the column instead would make
        every column ever sorted wider for good (widths never shrink)."""
        if key != self.sort_column:
            return label
        if cell_len(label) + 1 <= width:
            return label + self._arrow()
        return set_cell_size(label, max(0, width - 1)) + self._arrow()

    class SortChanged(Message):
        """The sort column or direction changed."""

        def __init__(self, table: LiveTable) -> None:
            super().__init__()
            self.table = table

    # -- cursor and mouse ------------------------------------------------------------------
    def move_cursor(self, row: int) -> None:
        """Put the row cursor on display row ``row`` (clamped) and scroll it into view."""
        old = self.cursor_row
        self.cursor_row = max(0, min(row, self.row_count - 1))
        if self.cursor_row != old:
            self._refresh_rows((old, self.cursor_row))
        self._scroll_to_cursor()

    def _scroll_to_cursor(self) -> None:
        visible = max(1, self.size.height - 1)
        top = int(self.scroll_y)
        if self.cursor_row < top:
            self.scroll_to(y=self.cursor_row, animate=False)
        elif self.cursor_row >= top + visible:
            self.scroll_to(y=self.cursor_row - visible + 1, animate=False)

    def action_cursor_up(self) -> None:
        self.move_cursor(self.cursor_row - 1)

    def action_cursor_down(self) -> None:
        self.move_cursor(self.cursor_row + 1)

    def action_page_up(self) -> None:
        self.move_cursor(self.cursor_row - max(1, self.size.height - 2))

    def action_page_down(self) -> None:
        self.move_cursor(self.cursor_row + max(1, self.size.height - 2))

    def action_cursor_home(self) -> None:
        self.move_cursor(0)

    def action_cursor_end(self) -> None:
        self.move_cursor(self.row_count - 1)

    def on_click(self, event: events.Click) -> None:
        offset = event.get_content_offset(self)
        if offset is None:
            return
        if offset.y == 0:  # the header: sort by that column (the same one: reverse)
            x = offset.x + int(self.scroll_x)
            for (key, _), width in zip(self._columns, self._widths, strict=True):
                x -= width + 2 * PAD
                if x < 0:
                    self._set_sort(key, not self.sort_reverse if key == self.sort_column
                                   else False)
                    break
        elif (row := offset.y - 1 + int(self.scroll_y)) < self.row_count:
            self.move_cursor(row)

    def watch_has_focus(self, focus: bool) -> None:
        # The cursor row's style depends on the focus: that line only.
        super().watch_has_focus(focus)
        self._refresh_rows((self.cursor_row,))

    # -- drawing ---------------------------------------------------------------------------
    def _line_signatures(self) -> list[tuple[str, int]]:
        return [(k, self.rows[k].version) for k in self._order]

    def _after_change(self, before: list[tuple[str, int]], widths: list[int]) -> None:
        """Repaint the screen lines whose row, or whose row's cells, changed."""
        if self.cursor_row >= self.row_count:
            self.cursor_row = max(0, self.row_count - 1)
        size = Size(sum(widths) + 2 * PAD * len(widths), self.row_count + 1)
        if widths != self._widths:
            self._widths = widths
            self.virtual_size = size
            self.refresh()  # every line moves: all of it
            return
        if size != self.virtual_size:
            self.virtual_size = size
        after = self._line_signatures()
        changed = [i for i in range(max(len(before), len(after)))
                   if i >= len(before) or i >= len(after) or before[i] != after[i]]
        self._refresh_rows(changed)

    def _refresh_rows(self, rows: Iterable[int]) -> None:
        """Repaint the screen lines of display rows ``rows`` that are in view, as few
        regions as possible (runs of adjacent lines)."""
        if not self.is_mounted:
            return
        top, height = int(self.scroll_y), self.size.height
        width = max(self.size.width, self.virtual_size.width)
        lines = sorted({r - top + 1 for r in rows if 1 <= r - top + 1 < height})
        start = prev = None
        for y in [*lines, None]:
            if y is not None and prev is not None and y == prev + 1:
                prev = y
                continue
            if start is not None and prev is not None:
                self.refresh(Region(0, start, width, prev - start + 1))
            start = prev = y

    def _cell_segments(self, cell: Cell, width: int, style: Style) -> list[Segment]:
        """One padded cell, ``width`` columns of text, in ``style`` (the cell's own styles
        over it); cached by value."""
        key = (_value_key(cell), width, style)
        got = self._cell_cache.get(key)
        if got is not None:
            return got
        pad = " " * PAD
        if isinstance(cell, Text):
            text = cell.copy()
            text.truncate(width, overflow="ellipsis", pad=True)
            text.end = ""
            # Text.render gives the spans' styles only: the text's own style goes under them.
            console = self.app.console
            own = console.get_style(cell.style, default=Style.null()) if cell.style else None
            inner = list(Segment.apply_style(text.render(console),
                                             style + own if own else style))
        else:
            inner = [Segment(set_cell_size(cell, width), style)]
        got = [Segment(pad, style), *inner, Segment(pad, style)]
        if len(self._cell_cache) > 20000:
            self._cell_cache.clear()
        self._cell_cache[key] = got
        return got

    def _header_strip(self, style: Style) -> Strip:
        key = (style, tuple(self._widths), tuple(self._columns), self.sort_column,
               self.sort_reverse)
        if self._header is None or self._header[0] != key:
            segs = [s for (col, label), w in zip(self._columns, self._widths, strict=True)
                    for s in self._cell_segments(self.header_label(col, label, w), w, style)]
            self._header = (key, Strip(segs))
        return self._header[1]

    def _row_strip(self, row: LiveRow, style: Style) -> Strip:
        key = (row.version, style, tuple(self._widths))
        if row.strip is None or row.strip_key != key:
            segs = [s for cell, w in zip(row.cells, self._widths, strict=True)
                    for s in self._cell_segments(cell, w, style)]
            row.strip, row.strip_key = Strip(segs), key
        return row.strip

    def render_line(self, y: int) -> Strip:
        self.lines_rendered += 1
        width = self.size.width
        scroll_x, scroll_y = self.scroll_offset
        base = self.rich_style
        if y == 0:
            strip = self._header_strip(
                base + self.get_component_rich_style("live-table--header"))
        elif (index := scroll_y + y - 1) < len(self._order):
            style = base
            if index == self.cursor_row:
                style = base + self.get_component_rich_style("live-table--cursor")
            strip = self._row_strip(self.rows[self._order[index]], style)
        else:
            return Strip.blank(width, base)
        return strip.crop_extend(scroll_x, scroll_x + width, base)
