"""CSV log of every estimate: one row per frame per marker, robot and rejected reference.

Header (exactly): ``frame,timestamp,algorithm,kind,id,x,y,z,yaw,error,refs``. Metres,
radians, seconds. ``kind`` is ``marker`` (id = marker id), ``robot`` (id = robot name) or
``rejected`` (id = a reference marker a robust estimator rejected; ``error`` = how far it
disagrees with the map, m) or ``plane`` (id = a marker with no known plane, neither in the map
nor on a configured robot: where ``estimator.unknown_plane`` put it; ``x,y,z`` = the unit
normal of the chosen plane and ``error`` its offset d, m, of ``normal . p = d`` in the world
frame; all four empty when the marker was estimated free). Each frame's rows go out in one
``write`` call and are flushed, so a killed daemon leaves only whole rows.
"""

from __future__ import annotations

import contextlib
import math
import os
from pathlib import Path

from kmea.recordings import wholewrite

HEADER = "frame,timestamp,algorithm,kind,id,x,y,z,yaw,error,refs"
COLUMNS = HEADER.split(",")


def _f(v: float | None, fmt: str) -> str:
    if v is None or not math.isfinite(v):
        return ""
    return format(v, fmt) if v != 0 else format(0.0, fmt)


def row(frame: int, timestamp: float, algorithm: str, kind: str, ident: object,
        x: float | None, y: float | None, z: float | None, yaw: float | None,
        error: float | None, refs: int) -> str:
    """One CSV line (with newline). Positions and errors to 0.1 um, angles to 1 urad."""
    return (f"{frame},{_f(timestamp, '.6f')},{algorithm},{kind},{ident},{_f(x, '.7f')},"
            f"{_f(y, '.7f')},{_f(z, '.7f')},{_f(yaw, '.6f')},{_f(error, '.7f')},{refs}\n")


def ends_whole(path: Path) -> bool:
    """The file ends with a newline (its last row is whole), or is empty."""
    with open(path, "rb") as f:
        if f.seek(0, os.SEEK_END) == 0:
            return True
        f.seek(-1, os.SEEK_END)
        return f.read(1) == b"\n"


def has_header(path: Path) -> bool:
    """The file is a CSV log of this format (its first line is :data:`HEADER`)."""
    with open(path, "rb") as f:
        return f.readline(len(HEADER) + 2).rstrip(b"\r\n") == HEADER.encode()


class CsvLog:
    """An open CSV log. ``write_rows`` takes the lines of one frame.

    append: continue an existing log of this format (no second header; the caller checks
    :func:`has_header` and :func:`ends_whole`); else the file is created (or emptied).
    """

    def __init__(self, path: str | Path, append: bool = False) -> None:
        self.path = Path(path)
        if self.path.parent and not self.path.parent.exists():
            self.path.parent.mkdir(parents=True, exist_ok=True)
        # Unbuffered binary file: one os-level write per frame (whole rows or nothing).
        self._f = wholewrite.open_output(self.path, append)
        self.appended = append
        self._end = self._f.seek(0, os.SEEK_END) if append else 0
        self.rows = 0
        self.mode = "create"  # how it was started: create, append, new name
        self.bytes = 0
        self.part = 1  # its part of a log cut by log.part_mb / part_min
        if not append:
            try:
                self._write((HEADER + "\n").encode())
            except OSError:
                self._f.close()
                raise

    def _write(self, data: bytes) -> None:
        wholewrite.write_whole(self._f, data, self._end)
        self._end += len(data)
        self.bytes += len(data)

    @property
    def size(self) -> int:
        """Bytes in the file (a continued log's earlier rows included)."""
        return self._end

    def write_rows(self, lines: list[str]) -> None:
        if not lines:
            return
        self._write("".join(lines).encode())
        self.rows += len(lines)

    def close(self) -> None:
        if not self._f.closed:
            with contextlib.suppress(OSError):
                os.fsync(self._f.fileno())
            self._f.close()

    @property
    def closed(self) -> bool:
        return self._f.closed
