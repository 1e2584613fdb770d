"""A DataTable that is kept in sync with live data in place (rows keyed, never rebuilt)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from rich.text import Text
from textual.binding import Binding
from textual.message import Message
from textual.widgets import DataTable

DASH = "-"


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
    try:
        hash(value)
    except TypeError:
        return ("R", repr(value))
    return value


class LiveTable(DataTable):
    """Rows keyed by a string; :meth:`sync` adds, updates (``update_cell``) and removes rows.

    Columns are ``(key, label)`` pairs. Sorting: ``s`` cycles the sort column, ``S`` reverses
    it; the sort value of a row comes from ``sort_value(raw_row, column_key)``.
    """

    BINDINGS = [
        Binding("s", "cycle_sort", "Sort col"),
        Binding("S", "reverse_sort", "Reverse", show=False),
    ]

    def __init__(self, columns: Sequence[tuple[str, str]], *,
                 sort_value: Callable[[dict[str, Any], str], Any] | None = None,
                 sort_column: str | None = None, id: str | None = None) -> None:
        super().__init__(id=id, cursor_type="row", zebra_stripes=False)
        self._columns = list(columns)
        self._sort_value = sort_value
        self.sort_column = sort_column or self._columns[0][0]
        self.sort_reverse = False
        self.raw: dict[str, dict[str, Any]] = {}
        self._cells: dict[str, tuple[str | Text, ...]] = {}  # cells last shown, per row
        self._value_cache: dict[tuple, Any] = {}  # rendered cells by value (_render_cell)
        self._line_cache_by_value: dict[tuple, Any] = {}  # row lines by value
        # Counters the tests read to prove rows are updated in place, not rebuilt.
        self.rows_added = 0
        self.rows_removed = 0
        self.cells_updated = 0

    def on_mount(self) -> None:
        for key, label in self._columns:
            self.add_column(label, key=key)

    @property
    def column_keys(self) -> list[str]:
        return [k for k, _ in self._columns]

    def sync(self, rows: dict[str, tuple[dict[str, Any], Sequence[str | Text]]]) -> None:
        """Make the table show exactly ``rows``: {key: (raw values, cells in column order)}.

        Only cells that changed are updated (``update_cell``), inside one batch update; the
        rows are sorted again only when a row came or went or a sort value changed.
        """
        keys = self.column_keys
        resort = False
        with self.app.batch_update():
            for key, (raw, cells) in rows.items():
                old = self.raw.get(key)
                self.raw[key] = raw
                cells = tuple(cells)
                if key in self.rows:
                    last = self._cells.get(key)
                    if last == cells:
                        continue  # nothing changed in this row: not even a cell lookup
                    for col, value, before in zip(keys, cells, last or (None,) * len(keys),
                                                  strict=True):
                        if before != value:
                            self.update_cell(key, col, value)
                            self.cells_updated += 1
                    if old is None or self._sort_of(old) != self._sort_of(raw):
                        resort = True
                else:
                    self.add_row(*cells, key=key)
                    self.rows_added += 1
                    resort = True
                self._cells[key] = cells
            for row_key in list(self.rows):
                if row_key.value not in rows:
                    self.remove_row(row_key)
                    self.raw.pop(row_key.value or "", None)
                    self._cells.pop(row_key.value or "", None)
                    self.rows_removed += 1
            if resort:
                self.apply_sort()

    def _render_cell(self, row_index: int, column_index: int, base_style: Any, width: int,
                     cursor: bool = False, hover: bool = False) -> Any:
        """DataTable's cell rendering, cached by the cell's *value*.

        DataTable keys its cell cache on a table-wide update counter: one ``update_cell``
        makes it render every visible cell again through Rich (~1 ms each; a 40-row
        markers table at 4 Hz was a quarter of a core). A cell whose value, place, width
        and style did not change renders to the same segments, so they are reused.
        """
        if row_index < 0 or column_index < 0:  # header and labels: DataTable's own cache
            return super()._render_cell(row_index, column_index, base_style, width, cursor,
                                        hover)
        row_key = self._row_locations.get_key(row_index)
        column_key = self._column_locations.get_key(column_index)
        value = self._data.get(row_key, {}).get(column_key)
        key = (row_key, column_key, _value_key(value), row_index, column_index, base_style,
               width, cursor, hover, self._show_hover_cursor, self.show_cursor,
               self._pseudo_class_state)
        lines = self._value_cache.get(key)
        if lines is None:
            if len(self._value_cache) > 20000:
                self._value_cache.clear()
            lines = self._value_cache[key] = super()._render_cell(
                row_index, column_index, base_style, width, cursor, hover)
        return lines

    def _render_line_in_row(self, row_key: Any, line_no: int, base_style: Any,
                            cursor_location: Any, hover_location: Any) -> Any:
        """DataTable's row line, cached by the row's values (its own cache is keyed on the
        table-wide update counter too: every visible line was joined again after any
        update). The key holds everything the line depends on: the row's cells and place,
        the column widths, the cursor and hover when they are on this row, the styles."""
        if row_key not in self._row_locations or row_key.value not in self._cells:
            return super()._render_line_in_row(row_key, line_no, base_style,
                                               cursor_location, hover_location)
        row_index = self._row_locations.get(row_key)
        widths = tuple(c.get_render_width(self) for c in self.ordered_columns)
        key = (row_key, line_no, base_style, row_index,
               tuple(_value_key(v) for v in self._cells[row_key.value]), widths,
               cursor_location if cursor_location.row == row_index else None,
               hover_location if hover_location.row == row_index else None,
               self.cursor_type, self.show_cursor, self._show_hover_cursor,
               self._pseudo_class_state, self.fixed_columns, self.fixed_rows,
               self.zebra_stripes, self.show_row_labels)
        got = self._line_cache_by_value.get(key)
        if got is None:
            if len(self._line_cache_by_value) > 5000:
                self._line_cache_by_value.clear()
            got = self._line_cache_by_value[key] = super()._render_line_in_row(
                row_key, line_no, base_style, cursor_location, hover_location)
        return got

    def _sort_of(self, raw: dict[str, Any]) -> Any:
        col = self.sort_column
        return self._sort_value(raw, col) if self._sort_value else raw.get(col)

    def apply_sort(self) -> None:
        if self.row_count < 2:
            return
        col = self.sort_column

        def value(row_key_cell: Any) -> Any:
            raw = self.raw.get(str(row_key_cell), {})
            v = self._sort_value(raw, col) if self._sort_value else raw.get(col)
            # Missing values sort last whatever the direction.
            missing = v is None
            if self.sort_reverse:
                missing = not missing
            return (missing, v if v is not None else 0)

        # The first column holds the row key's text, which identifies the raw row.
        self.sort(self.column_keys[0], key=value, reverse=self.sort_reverse)

    def action_cycle_sort(self) -> None:
        keys = self.column_keys
        self.sort_column = keys[(keys.index(self.sort_column) + 1) % len(keys)]
        self.apply_sort()
        self.post_message(self.SortChanged(self))

    def action_reverse_sort(self) -> None:
        self.sort_reverse = not self.sort_reverse
        self.apply_sort()
        self.post_message(self.SortChanged(self))

    def on_data_table_header_selected(self, event: DataTable.HeaderSelected) -> None:
        key = event.column_key.value or self.sort_column
        if key == self.sort_column:
            self.sort_reverse = not self.sort_reverse
        else:
            self.sort_column, self.sort_reverse = key, False
        self.apply_sort()
        self.post_message(self.SortChanged(self))

    def sort_label(self) -> str:
        label = dict(self._columns).get(self.sort_column, self.sort_column)
        return f"sort {label}{'▼' if self.sort_reverse else '▲'}"

    class SortChanged(Message):
        """The sort column or direction changed."""

        def __init__(self, table: LiveTable) -> None:
            super().__init__()
            self.table = table
