"""A one-line textual progress bar on stderr (no dependency)."""

from __future__ import annotations

import sys
import time
from typing import TextIO


class Progress:
    """``label [#####.....] done/total  rate/s  ETA``; redrawn in place on a terminal,
    printed every tenth of the way otherwise (logs stay short). ``note``: a few words
    after it (e.g. markers seen so far), updated with :meth:`update`."""

    def __init__(self, total: int, label: str, unit: str = "frames",
                 stream: TextIO | None = None, enabled: bool = True) -> None:
        self.total = max(int(total), 0)
        self.label = label
        self.unit = unit
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled
        self.done = 0
        self.t0 = time.monotonic()
        self._tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._last_decile = -1
        self.note = ""

    def update(self, n: int = 1, note: str | None = None) -> None:
        self.done = min(self.done + n, self.total)
        if note is not None:
            self.note = note
        if not self.enabled:
            return
        if self._tty:
            self.stream.write("\r" + self._line())
            self.stream.flush()
        else:
            decile = (10 * self.done) // max(self.total, 1)
            if decile != self._last_decile:
                self._last_decile = decile
                self.stream.write(self._line() + "\n")
                self.stream.flush()

    def close(self) -> None:
        if self.enabled and self._tty:
            self.stream.write("\r" + self._line() + "\n")
            self.stream.flush()

    def _line(self) -> str:
        width = 30
        frac = self.done / self.total if self.total else 1.0
        bar = "#" * round(frac * width)
        dt = time.monotonic() - self.t0
        rate = self.done / dt if dt > 0 else 0.0
        eta = (self.total - self.done) / rate if rate > 0 else float("nan")
        eta_s = f"ETA {eta:5.0f} s" if eta == eta else "ETA     ? s"
        return (f"{self.label} [{bar:<{width}}] {self.done}/{self.total} {self.unit} "
                f"{rate:6.1f}/s {eta_s}" + (f"  {self.note}" if self.note else ""))
